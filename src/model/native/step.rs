//! The native decode step: `ComGraspTransformer.step` (training/.../models/transformer.py)
//! in Rust, on the weights of `transformer.native`, into buffers allocated once per state.
//!
//! Per step, for the four streams s (widths w_s, H heads of d_s = w_s / H):
//! * input: pos 0 `cond_s(text_emb)`, else `tok_s[token]`; plus `pos_s[pos]`;
//! * per layer l: before every layer but the first, part coordination
//!   `h_i <- LN_i(h_i + out_i(MLP(concat_{j != i} in_j(h_j))))` (the shared MLP runs on the
//!   four concatenations at once, so its weights are read once); then the pre-LN block
//!   `h += proj(attn(LN1 h)); h += fc2(GELU(fc1(LN2 h)))`, the attention writing the new
//!   k/v row into slot `pos` of the state's cache and attending over slots `0..=pos`;
//! * `logits_s = head_s(LN_f h_s)`.
//!
//! The graph instead attends over the cache's slots `< pos` plus the new row as a separate
//! score; that is the same softmax (masked slots weigh exactly 0), up to float rounding.
//! LayerNorm eps is PyTorch's default 1e-5.
use super::kernels::{add_assign, dot, gelu_erf, gemm, gemv, layer_norm, softmax};
use super::weights::{Matrix, Tensors};
use crate::bundle::manifest::{Manifest, NativeSpec, N_STREAMS};
use crate::bundle::BundleSource;
use crate::error::{Error, Result};

const LN_EPS: f32 = 1e-5;

struct Linear {
    w: Matrix,
    b: Option<Vec<f32>>,
}

impl Linear {
    fn load(t: &Tensors, name: &str, rows: usize, cols: usize, bias: bool) -> Result<Linear> {
        Ok(Linear {
            w: t.matrix(&format!("{name}.weight"), rows, cols)?,
            b: if bias { Some(t.vector(&format!("{name}.bias"), rows)?) } else { None },
        })
    }

    fn run(&self, x: &[f32], y: &mut [f32]) {
        gemv(&self.w, x, self.b.as_deref(), y)
    }
}

struct Norm {
    w: Vec<f32>,
    b: Vec<f32>,
}

impl Norm {
    fn load(t: &Tensors, name: &str, n: usize) -> Result<Norm> {
        Ok(Norm { w: t.vector(&format!("{name}.weight"), n)?, b: t.vector(&format!("{name}.bias"), n)? })
    }

    fn run(&self, x: &[f32], out: &mut [f32]) {
        layer_norm(x, &self.w, &self.b, LN_EPS, out)
    }
}

struct Block {
    ln1: Norm,
    qkv: Linear,
    proj: Linear,
    ln2: Norm,
    fc1: Linear,
    fc2: Linear,
}

struct Stream {
    cond: Linear,
    tok: Matrix,
    pos: Vec<f32>,
    blocks: Vec<Block>,
    ln_f: Norm,
    head: Matrix,
}

struct Coord {
    inp: Vec<Linear>,
    mlp: [Linear; 3],
    out: Vec<Linear>,
    norm: Vec<Norm>,
}

/// Sizes of the network (from the manifest; the hidden widths from the tensors' shapes).
#[derive(Clone, Copy, Debug)]
struct Dims {
    n_layers: usize,
    n_heads: usize,
    slots: usize,
    d_text: usize,
    widths: [usize; N_STREAMS],
    head_dims: [usize; N_STREAMS],
    vocab: [usize; N_STREAMS],
    /// The blocks' MLP width per stream (mlp_ratio x width).
    hidden: [usize; N_STREAMS],
    coord_width: usize,
    coord_hidden: usize,
}

/// The step's weights, shared by all states of a model.
pub(crate) struct NativeStep {
    d: Dims,
    streams: Vec<Stream>,
    coord: Vec<Coord>,
    /// 1/sqrt(head_dim) per stream, as the graph's constant (computed in f64, then rounded).
    scale: [f32; N_STREAMS],
    bytes: usize,
}

/// One generation's KV cache and scratch buffers (everything `step` writes).
pub(crate) struct NativeStepState {
    /// Per stream, (L, H, S, D) row-major: the layout of the graph's cache inputs.
    k: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    h: Vec<Vec<f32>>,
    x: Vec<Vec<f32>>,
    qkv: Vec<f32>,
    att: Vec<f32>,
    tmp: Vec<f32>,
    mlp: Vec<f32>,
    scores: Vec<f32>,
    /// Coordination: the four projections, the four concatenations, the MLP's activations.
    cp: Vec<f32>,
    ccat: Vec<f32>,
    ch1: Vec<f32>,
    ch2: Vec<f32>,
    cm: Vec<f32>,
}

impl NativeStep {
    /// Loads every tensor of `spec`, checking it against the manifest's sizes; any missing,
    /// extra, misshapen, mistyped or non-finite tensor is an `Error::Bundle`.
    pub(crate) fn load(src: &BundleSource, m: &Manifest, spec: &NativeSpec) -> Result<NativeStep> {
        let t = &m.transformer;
        let tensors = Tensors::new(src, spec);
        let err = |msg: String| Error::bundle(src.path_of(&spec.dir), msg);
        if t.widths.len() != N_STREAMS || t.head_dims.len() != N_STREAMS {
            return Err(err(format!("the transformer has {} widths, the native step needs {N_STREAMS}", t.widths.len())));
        }
        let widths: [usize; N_STREAMS] = std::array::from_fn(|i| t.widths[i]);
        let head_dims: [usize; N_STREAMS] = std::array::from_fn(|i| t.head_dims[i]);
        for s in 0..N_STREAMS {
            if widths[s] == 0 || head_dims[s] * t.n_heads != widths[s] {
                return Err(err(format!("stream {s}: width {} is not n_heads {} x head_dim {}", widths[s], t.n_heads, head_dims[s])));
            }
        }
        if t.n_layers == 0 || t.cache_slots == 0 || t.d_text == 0 {
            return Err(err("the transformer needs at least one layer, one slot and a text width".into()));
        }
        // Hidden widths are not in the manifest: read them from the first tensors' shapes
        // (every other tensor is then checked against them).
        let first_axis = |name: &str| -> Result<usize> {
            tensors.shape(name)?.first().copied().ok_or_else(|| err(format!("native tensor {name} is a scalar")))
        };
        let hidden: [usize; N_STREAMS] = {
            let mut h = [0; N_STREAMS];
            for (s, hs) in h.iter_mut().enumerate() {
                *hs = first_axis(&format!("streams.{s}.blocks.0.mlp.0.weight"))?;
            }
            h
        };
        let (coord_width, coord_hidden) = if t.n_layers > 1 {
            (first_axis("coord.0.inp.0.weight")?, first_axis("coord.0.mlp.0.weight")?)
        } else {
            (0, 0)
        };
        let d = Dims {
            n_layers: t.n_layers, n_heads: t.n_heads, slots: t.cache_slots, d_text: t.d_text, widths, head_dims,
            vocab: m.vocab_sizes(), hidden, coord_width, coord_hidden,
        };
        // Guard the products used for buffer sizes against absurd manifests.
        d.n_layers.checked_mul(d.slots).and_then(|v| v.checked_mul(widths.iter().max().copied()?))
            .filter(|&v| v <= 1 << 32)
            .ok_or_else(|| err("the KV cache would be absurdly large".into()))?;

        let mut expected = std::collections::BTreeSet::new();
        let mut note = |n: String| -> String {
            expected.insert(n.clone());
            n
        };
        let mut streams = Vec::with_capacity(N_STREAMS);
        for s in 0..N_STREAMS {
            let (w, v, hid) = (widths[s], d.vocab[s], hidden[s]);
            let p = |n: &str| format!("streams.{s}.{n}");
            let lin = |t: &Tensors, n: String, rows, cols, bias| -> Result<Linear> { Linear::load(t, &n, rows, cols, bias) };
            let mut blocks = Vec::with_capacity(d.n_layers);
            for l in 0..d.n_layers {
                let b = |n: &str| format!("streams.{s}.blocks.{l}.{n}");
                for n in ["ln1", "attn.qkv", "attn.proj", "ln2", "mlp.0", "mlp.2"] {
                    note(b(&format!("{n}.weight")));
                    note(b(&format!("{n}.bias")));
                }
                blocks.push(Block {
                    ln1: Norm::load(&tensors, &b("ln1"), w)?,
                    qkv: lin(&tensors, b("attn.qkv"), 3 * w, w, true)?,
                    proj: lin(&tensors, b("attn.proj"), w, w, true)?,
                    ln2: Norm::load(&tensors, &b("ln2"), w)?,
                    fc1: lin(&tensors, b("mlp.0"), hid, w, true)?,
                    fc2: lin(&tensors, b("mlp.2"), w, hid, true)?,
                });
            }
            for n in ["pos", "cond.weight", "cond.bias", "tok.weight", "ln_f.weight", "ln_f.bias", "head.weight"] {
                note(p(n));
            }
            let pos_shape = tensors.shape(&p("pos"))?;
            if pos_shape != [d.slots, w] {
                return Err(err(format!("native tensor {} has shape {pos_shape:?}, expected [{}, {w}]", p("pos"), d.slots)));
            }
            streams.push(Stream {
                cond: lin(&tensors, p("cond"), w, d.d_text, true)?,
                tok: tensors.matrix(&p("tok.weight"), v, w)?,
                pos: tensors.vector(&p("pos"), d.slots * w)?,
                blocks,
                ln_f: Norm::load(&tensors, &p("ln_f"), w)?,
                head: tensors.matrix(&p("head.weight"), v, w)?,
            });
        }
        let (cw, ch) = (coord_width, coord_hidden);
        let mut coord = Vec::with_capacity(d.n_layers.saturating_sub(1));
        for c in 0..d.n_layers.saturating_sub(1) {
            let n = |x: &str| format!("coord.{c}.{x}");
            for x in ["mlp.0", "mlp.2", "mlp.4"] {
                note(n(&format!("{x}.weight")));
                note(n(&format!("{x}.bias")));
            }
            let mut inp = Vec::new();
            let mut out = Vec::new();
            let mut norm = Vec::new();
            for s in 0..N_STREAMS {
                for x in ["inp", "out", "norm"] {
                    note(n(&format!("{x}.{s}.weight")));
                    note(n(&format!("{x}.{s}.bias")));
                }
                inp.push(Linear::load(&tensors, &n(&format!("inp.{s}")), cw, widths[s], true)?);
                out.push(Linear::load(&tensors, &n(&format!("out.{s}")), widths[s], cw, true)?);
                norm.push(Norm::load(&tensors, &n(&format!("norm.{s}")), widths[s])?);
            }
            coord.push(Coord {
                inp,
                mlp: [
                    Linear::load(&tensors, &n("mlp.0"), ch, (N_STREAMS - 1) * cw, true)?,
                    Linear::load(&tensors, &n("mlp.2"), ch, ch, true)?,
                    Linear::load(&tensors, &n("mlp.4"), cw, ch, true)?,
                ],
                out,
                norm,
            });
        }
        if let Some(extra) = tensors.names().find(|n| !expected.contains(*n)) {
            return Err(err(format!("native weights hold tensor {extra}, which the step does not use")));
        }
        let mut bytes = 0;
        for s in &streams {
            bytes += s.cond.w.bytes() + s.head.bytes();
            for b in &s.blocks {
                bytes += b.qkv.w.bytes() + b.proj.w.bytes() + b.fc1.w.bytes() + b.fc2.w.bytes();
            }
        }
        for c in &coord {
            bytes += c.mlp.iter().chain(&c.inp).chain(&c.out).map(|l| l.w.bytes()).sum::<usize>();
        }
        let scale = std::array::from_fn(|s| (1.0 / (head_dims[s] as f64).sqrt()) as f32);
        Ok(NativeStep { d, streams, coord, scale, bytes })
    }

    /// Bytes of weight matrices one step reads.
    pub(crate) fn weight_bytes(&self) -> usize {
        self.bytes
    }

    /// A state with a zero cache and every scratch buffer allocated.
    pub(crate) fn new_state(&self) -> NativeStepState {
        let d = &self.d;
        let wmax = *d.widths.iter().max().unwrap_or(&0);
        let hmax = *d.hidden.iter().max().unwrap_or(&0);
        let cache = |s: usize| vec![0.0f32; d.n_layers * d.slots * d.widths[s]];
        NativeStepState {
            k: (0..N_STREAMS).map(cache).collect(),
            v: (0..N_STREAMS).map(cache).collect(),
            h: d.widths.iter().map(|&w| vec![0.0; w]).collect(),
            x: d.widths.iter().map(|&w| vec![0.0; w]).collect(),
            qkv: vec![0.0; 3 * wmax],
            att: vec![0.0; wmax],
            tmp: vec![0.0; wmax],
            mlp: vec![0.0; hmax],
            scores: vec![0.0; d.slots],
            cp: vec![0.0; N_STREAMS * d.coord_width],
            ccat: vec![0.0; N_STREAMS * (N_STREAMS - 1) * d.coord_width],
            ch1: vec![0.0; N_STREAMS * d.coord_hidden],
            ch2: vec![0.0; N_STREAMS * d.coord_hidden],
            cm: vec![0.0; N_STREAMS * d.coord_width],
        }
    }

    /// One step at `pos` (validated by the caller: `pos < slots`, rows `0..pos` filled,
    /// tokens inside the vocabularies, `text_emb` of `d_text` finite values); writes the
    /// logits into `logits` and the new k/v rows into the state's cache. No allocation.
    pub(crate) fn step(&self, st: &mut NativeStepState, tokens: [i64; N_STREAMS], pos: usize, text_emb: &[f32],
                       logits: &mut [Vec<f32>; N_STREAMS]) {
        let d = &self.d;
        for (s, sw) in self.streams.iter().enumerate() {
            let w = d.widths[s];
            let h = &mut st.h[s];
            if pos == 0 {
                sw.cond.run(text_emb, h);
            } else {
                sw.tok.row_into(tokens[s] as usize, h);
            }
            add_assign(h, &sw.pos[pos * w..(pos + 1) * w]);
        }
        for l in 0..d.n_layers {
            if l > 0 {
                self.coordinate(&self.coord[l - 1], st);
            }
            for s in 0..N_STREAMS {
                self.block(s, l, pos, st);
            }
        }
        for (s, sw) in self.streams.iter().enumerate() {
            let w = d.widths[s];
            sw.ln_f.run(&st.h[s], &mut st.x[s][..w]);
            gemv(&sw.head, &st.x[s], None, &mut logits[s]);
        }
    }

    fn block(&self, s: usize, l: usize, pos: usize, st: &mut NativeStepState) {
        let d = &self.d;
        let (w, hd, nh, slots) = (d.widths[s], d.head_dims[s], d.n_heads, d.slots);
        let b = &self.streams[s].blocks[l];
        let h = &mut st.h[s];
        let x = &mut st.x[s];
        b.ln1.run(h, x);
        let qkv = &mut st.qkv[..3 * w];
        b.qkv.run(x, qkv);
        let (q, kv) = qkv.split_at(w);
        let (k, v) = kv.split_at(w);
        let (ck, cv) = (&mut st.k[s], &mut st.v[s]);
        let att = &mut st.att[..w];
        for head in 0..nh {
            // cache (L, H, S, D): rows of this layer and head start at `base`
            let base = (l * nh + head) * slots * hd;
            let row = base + pos * hd;
            ck[row..row + hd].copy_from_slice(&k[head * hd..(head + 1) * hd]);
            cv[row..row + hd].copy_from_slice(&v[head * hd..(head + 1) * hd]);
            let qh = &q[head * hd..(head + 1) * hd];
            let scores = &mut st.scores[..=pos];
            for (t, sc) in scores.iter_mut().enumerate() {
                let kr = base + t * hd;
                *sc = dot(qh, &ck[kr..kr + hd]) * self.scale[s];
            }
            softmax(scores);
            let out = &mut att[head * hd..(head + 1) * hd];
            out.fill(0.0);
            for (t, &p) in scores.iter().enumerate() {
                let vr = base + t * hd;
                for (o, &vv) in out.iter_mut().zip(&cv[vr..vr + hd]) {
                    *o += p * vv;
                }
            }
        }
        let tmp = &mut st.tmp[..w];
        b.proj.run(att, tmp);
        add_assign(h, tmp);
        b.ln2.run(h, x);
        let mlp = &mut st.mlp[..d.hidden[s]];
        b.fc1.run(x, mlp);
        gelu_erf(mlp);
        b.fc2.run(mlp, tmp);
        add_assign(h, tmp);
    }

    fn coordinate(&self, c: &Coord, st: &mut NativeStepState) {
        let d = &self.d;
        let cw = d.coord_width;
        for s in 0..N_STREAMS {
            c.inp[s].run(&st.h[s], &mut st.cp[s * cw..(s + 1) * cw]);
        }
        // concatenation i: the other streams' projections in stream order
        let cat_len = (N_STREAMS - 1) * cw;
        for i in 0..N_STREAMS {
            let mut at = i * cat_len;
            for j in (0..N_STREAMS).filter(|&j| j != i) {
                st.ccat[at..at + cw].copy_from_slice(&st.cp[j * cw..(j + 1) * cw]);
                at += cw;
            }
        }
        gemm(&c.mlp[0].w, &st.ccat, N_STREAMS, c.mlp[0].b.as_deref(), &mut st.ch1);
        gelu_erf(&mut st.ch1);
        gemm(&c.mlp[1].w, &st.ch1, N_STREAMS, c.mlp[1].b.as_deref(), &mut st.ch2);
        gelu_erf(&mut st.ch2);
        gemm(&c.mlp[2].w, &st.ch2, N_STREAMS, c.mlp[2].b.as_deref(), &mut st.cm);
        for s in 0..N_STREAMS {
            let w = d.widths[s];
            let tmp = &mut st.tmp[..w];
            c.out[s].run(&st.cm[s * cw..(s + 1) * cw], tmp);
            add_assign(tmp, &st.h[s]);
            c.norm[s].run(tmp, &mut st.h[s]);
        }
    }
}

impl NativeStepState {
    /// Zeroes the cache (a new generation; no allocation).
    pub(crate) fn reset(&mut self) {
        for c in self.k.iter_mut().chain(self.v.iter_mut()) {
            c.fill(0.0);
        }
    }

    /// The cache of stream `s` as (k, v), each (L, H, S, D) row-major.
    #[allow(dead_code)]
    pub(crate) fn cache(&self, s: usize) -> (&[f32], &[f32]) {
        (&self.k[s], &self.v[s])
    }
}
