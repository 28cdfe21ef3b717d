//! The text encoder on the native kernels: a BERT encoder (all-MiniLM-L6-v2's layout:
//! embeddings + LayerNorm, then post-LN layers of self-attention and an exact-GELU MLP) on
//! the weights of `text_encoder.native` (export/text_encoder_export.py), the same function
//! as `text_encoder.onnx` to float rounding.
//!
//! Why: the text encoder was the only model of the default bundle that needed tract, and a
//! plugin built without tract is a third of the size (docs/performance.md, "Library size").
//! The word table may be int4 (`Table::I4`): a prompt reads a few dozen of its 30,522 rows,
//! which are unpacked as they are gathered.
//!
//! Only the prompt's real tokens are run. Padding is on the right and the exported graph
//! gives padded keys a `float32::MIN` bias, so no real token's state depends on them and
//! the pooling never reads their rows (the same argument as the tract path's real-tokens
//! form, `text_graph`). Runs on the calling thread: a prompt is encoded once per engine
//! (`Pipeline::embedding` caches it) and costs about as much as one decode.
use super::gemm::gemm;
use super::kernels::{self, MatRef};
use super::weights::{Matrix, Table, Tensors};
use crate::bundle::manifest::{TextEncoderSpec, TextNativeSpec, MANIFEST_FILE};
use crate::bundle::BundleSource;
use crate::error::{Error, Result};

struct Layer {
    /// Query, key and value stacked (`3 * hidden` rows): one product per layer.
    qkv: Matrix,
    qkv_bias: Vec<f32>,
    out: Matrix,
    out_bias: Vec<f32>,
    ln1: (Vec<f32>, Vec<f32>),
    up: Matrix,
    up_bias: Vec<f32>,
    down: Matrix,
    down_bias: Vec<f32>,
    ln2: (Vec<f32>, Vec<f32>),
}

/// A loaded native BERT encoder; immutable, shared by every stream.
pub(crate) struct NativeText {
    hidden: usize,
    heads: usize,
    inner: usize,
    eps: f32,
    word: Table,
    /// `(max_tokens, hidden)`: positions past the tokenizer's length are never used.
    positions: Vec<f32>,
    /// `(type_vocab, hidden)`.
    types: Vec<f32>,
    ln: (Vec<f32>, Vec<f32>),
    layers: Vec<Layer>,
}

impl std::fmt::Debug for NativeText {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NativeText")
            .field("hidden", &self.hidden)
            .field("heads", &self.heads)
            .field("layers", &self.layers.len())
            .field("vocab", &self.word.rows())
            .finish_non_exhaustive()
    }
}

/// Stacks int8 (or f32) matrices of the same width row-wise.
fn stack(parts: Vec<Matrix>) -> Result<Matrix> {
    let cols = parts[0].cols();
    let rows = parts.iter().map(Matrix::rows).sum();
    let mut out = match &parts[0] {
        Matrix::I8 { .. } => Matrix::I8 { rows, cols, q: Vec::new(), scale: Vec::new() },
        Matrix::F32 { .. } => Matrix::F32 { rows, cols, w: Vec::new() },
    };
    for p in parts {
        match (&mut out, p) {
            (Matrix::I8 { q, scale, .. }, Matrix::I8 { q: pq, scale: ps, .. }) => {
                q.extend(pq);
                scale.extend(ps);
            }
            (Matrix::F32 { w, .. }, Matrix::F32 { w: pw, .. }) => w.extend(pw),
            _ => return Err(Error::Inference("mixed int8 and f32 q/k/v".into())),
        }
    }
    Ok(out)
}

impl NativeText {
    /// Loads `t.native` (which the caller checked is present), checking every tensor's
    /// dtype and shape against the manifest's text encoder fields.
    pub(crate) fn load(src: &BundleSource, t: &TextEncoderSpec, spec: &TextNativeSpec) -> Result<NativeText> {
        let bad = |msg: String| Error::bundle(src.path_of(MANIFEST_FILE), format!("text_encoder.native: {msg}"));
        let hidden = t.hidden;
        if t.pool_output != "last_hidden_state" || t.hidden != t.dim {
            return Err(bad(format!(
                "the native encoder computes last_hidden_state ({} wide); the manifest pools {:?} of width {}",
                t.hidden, t.pool_output, t.dim
            )));
        }
        if spec.activation != "gelu" {
            return Err(bad(format!("activation {:?} is not supported (only \"gelu\")", spec.activation)));
        }
        if spec.heads == 0 || !hidden.is_multiple_of(spec.heads) {
            return Err(bad(format!("{} heads do not divide the width {hidden}", spec.heads)));
        }
        if !(spec.layer_norm_eps.is_finite() && spec.layer_norm_eps > 0.0) {
            return Err(bad(format!("layer_norm_eps {} is not a positive number", spec.layer_norm_eps)));
        }
        let weights = spec.weights();
        let w = Tensors::new(src, &weights);
        let vocab = w.shape("embeddings.word_embeddings.weight")?.first().copied().unwrap_or(0);
        let word = w.table("embeddings.word_embeddings.weight", vocab, hidden)?;
        let positions = w.vector("embeddings.position_embeddings.weight", t.max_tokens * hidden)?;
        let n_types = w.shape("embeddings.token_type_embeddings.weight")?.first().copied().unwrap_or(0);
        let types = w.vector("embeddings.token_type_embeddings.weight", n_types * hidden)?;
        let norm = |p: &str| -> Result<(Vec<f32>, Vec<f32>)> {
            Ok((w.vector(&format!("{p}.weight"), hidden)?, w.vector(&format!("{p}.bias"), hidden)?))
        };
        let ln = norm("embeddings.LayerNorm")?;
        let n_layers =
            (0..).take_while(|i| w.shape(&format!("layers.{i}.attention.self.query.weight")).is_ok()).count();
        if n_layers == 0 {
            return Err(bad("no layers (layers.0.attention.self.query.weight)".into()));
        }
        let inner = w.shape("layers.0.intermediate.dense.weight")?.first().copied().unwrap_or(0);
        let mut layers = Vec::with_capacity(n_layers);
        for i in 0..n_layers {
            let p = format!("layers.{i}");
            let lin = |name: &str, rows: usize, cols: usize| -> Result<(Matrix, Vec<f32>)> {
                let m = w.matrix(&format!("{p}.{name}.weight"), rows, cols)?;
                Ok((m, w.vector(&format!("{p}.{name}.bias"), rows)?))
            };
            let (q, bq) = lin("attention.self.query", hidden, hidden)?;
            let (k, bk) = lin("attention.self.key", hidden, hidden)?;
            let (v, bv) = lin("attention.self.value", hidden, hidden)?;
            let (out, out_bias) = lin("attention.output.dense", hidden, hidden)?;
            let (up, up_bias) = lin("intermediate.dense", inner, hidden)?;
            let (down, down_bias) = lin("output.dense", hidden, inner)?;
            layers.push(Layer {
                qkv: stack(vec![q, k, v])?,
                qkv_bias: [bq, bk, bv].concat(),
                out,
                out_bias,
                ln1: norm(&format!("{p}.attention.output.LayerNorm"))?,
                up,
                up_bias,
                down,
                down_bias,
                ln2: norm(&format!("{p}.output.LayerNorm"))?,
            });
        }
        // Exactly the tensors read above: a stray name means a layout this code does not run.
        let used = 5 + 16 * n_layers;
        if weights.tensors.len() != used {
            return Err(bad(format!(
                "lists {} tensors, a {n_layers}-layer BERT encoder has {used}",
                weights.tensors.len()
            )));
        }
        Ok(NativeText {
            hidden,
            heads: spec.heads,
            inner,
            eps: spec.layer_norm_eps as f32,
            word,
            positions,
            types,
            ln,
            layers,
        })
    }

    /// The token states `(ids.len(), hidden)` of the first tokens of a prompt (no padding
    /// among them; at most `max_tokens`). Ids and type ids out of range are errors.
    pub(crate) fn token_states(&self, ids: &[i64], type_ids: &[i64]) -> Result<Vec<f32>> {
        let (h, n) = (self.hidden, ids.len());
        if n * h > self.positions.len() || type_ids.len() != n {
            return Err(Error::Inference(format!("{n} tokens for a {}-token encoder", self.positions.len() / h)));
        }
        let mut x = vec![0f32; n * h];
        let mut row = vec![0f32; h];
        for (s, (&id, &ty)) in ids.iter().zip(type_ids).enumerate() {
            let id = usize::try_from(id).ok().filter(|&i| i < self.word.rows());
            let ty = usize::try_from(ty).ok().filter(|&t| (t + 1) * h <= self.types.len());
            let (Some(id), Some(ty)) = (id, ty) else {
                return Err(Error::Inference(format!("token {s}: id {id:?} or type {ty:?} outside the tables")));
            };
            self.word.row_into(id, &mut row);
            for (c, v) in row.iter_mut().enumerate() {
                // The graph's order: (word + type) + position.
                *v = *v + self.types[ty * h + c] + self.positions[s * h + c];
            }
            kernels::layer_norm(&row, &self.ln.0, &self.ln.1, self.eps, &mut x[s * h..(s + 1) * h]);
        }

        let (heads, dh) = (self.heads, h / self.heads);
        let scale = 1.0 / (dh as f32).sqrt();
        let mut qkv = vec![0f32; n * 3 * h];
        let mut ctx = vec![0f32; n * h];
        let mut proj = vec![0f32; n * h];
        let mut inner = vec![0f32; n * self.inner];
        let mut scores = vec![0f32; n];
        for l in &self.layers {
            gemm(MatRef::from(&l.qkv), &x, h, n, Some(&l.qkv_bias), &mut qkv, 3 * h);
            for hd in 0..heads {
                for i in 0..n {
                    let q = &qkv[i * 3 * h + hd * dh..][..dh];
                    for (j, sc) in scores.iter_mut().enumerate() {
                        *sc = kernels::dot(q, &qkv[j * 3 * h + h + hd * dh..][..dh]) * scale;
                    }
                    kernels::softmax(&mut scores);
                    let c = &mut ctx[i * h + hd * dh..][..dh];
                    c.fill(0.0);
                    for (j, &p) in scores.iter().enumerate() {
                        for (o, &v) in c.iter_mut().zip(&qkv[j * 3 * h + 2 * h + hd * dh..][..dh]) {
                            *o += p * v;
                        }
                    }
                }
            }
            gemm(MatRef::from(&l.out), &ctx, h, n, Some(&l.out_bias), &mut proj, h);
            residual_norm(&mut x, &proj, &l.ln1, self.eps, h);
            gemm(MatRef::from(&l.up), &x, h, n, Some(&l.up_bias), &mut inner, self.inner);
            kernels::gelu_erf(&mut inner);
            gemm(MatRef::from(&l.down), &inner, self.inner, n, Some(&l.down_bias), &mut proj, h);
            residual_norm(&mut x, &proj, &l.ln2, self.eps, h);
        }
        Ok(x)
    }
}

/// `x = LayerNorm(x + y)` row by row (BERT's post-LN residual).
fn residual_norm(x: &mut [f32], y: &[f32], ln: &(Vec<f32>, Vec<f32>), eps: f32, h: usize) {
    let mut sum = vec![0f32; h];
    for (xr, yr) in x.chunks_exact_mut(h).zip(y.chunks_exact(h)) {
        for ((s, a), b) in sum.iter_mut().zip(xr.iter()).zip(yr) {
            *s = a + b;
        }
        kernels::layer_norm(&sum, &ln.0, &ln.1, eps, xr);
    }
}
