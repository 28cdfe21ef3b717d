//! The text encoder's ONNX graph in tract (cargo feature `onnx`): the path for bundles
//! without `text_encoder.native` (CLIP, the tiny test bundle) and the reference the native
//! encoder is checked against.
//!
//! Speed: the graph is loaded with two rewrites, each checked at load and each skipped
//! (falling back to the graph as exported, `graph::load`) where it does not apply:
//! * int8-stored embedding tables (`Gather(Cast(q) * s, ids)`, the layout written by
//!   `training/src/comgrasp_train/weight_quant.py`, one scale per row): tract's constant
//!   folding skips a node whose result is larger than both its inputs and 4 MiB (int8 ->
//!   f32 quadruples the size), so the 30522x384 word table was dequantized on every call
//!   (~70% of the time per prompt). The rewrite gathers first,
//!   `Cast(Gather(q, ids)) * Gather(s, ids)`: the same products, bit for bit, on the
//!   selected rows only (and the table stays int8 in memory).
//! * real tokens only ([`SequenceMode::RealTokens`]): the tokens the pooling reads are a
//!   prefix (padding is on the right) and the attention mask keeps padded keys out of every
//!   real token's state, so running the first `n` tokens gives them the states a run on all
//!   `max_tokens` gives (to float rounding, ~1e-6; the matmuls sum in another order). The
//!   sequence axis of the graph inputs is made symbolic and each `Reshape` target
//!   `[1, max_tokens, ..]` becomes `[1, 0, ..]` (0: copy the input's axis 1). Accepted only
//!   if every rewritten Reshape's input has the sequence on axis 1 (so at full length the
//!   graph is the exported one), the outputs come out `[1, S, width]`, and a probe prompt's
//!   states from its real tokens agree with the full-length run.
use std::collections::HashMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Arc;

use tract_onnx::pb;
use tract_onnx::prelude::{
    DatumType, Framework, InferenceFact, InferenceModelExt, IntoRunnable, TDim, TVec, Tensor, ToDim,
};
use tract_onnx::tract_hir::infer::Factoid;

use super::graph::{self, Plan};
use super::text::{SequenceMode, TokenizedText};
use crate::bundle::manifest::{Dtype, TextEncoderSpec};
use crate::bundle::BundleSource;
use crate::error::{Error, Result};

/// What each graph input carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Role {
    Ids,
    Mask,
    TypeIds,
    Positions,
}

/// The loaded graph and how it is fed.
pub(crate) struct GraphText {
    plan: Plan,
    pub(crate) mode: SequenceMode,
    /// Why a faster form of the graph was not used (diagnostics).
    pub(crate) fallback: Option<String>,
    roles: Vec<Role>,
    /// Index of `pool_output` among the graph outputs, and its width.
    pool_index: usize,
    width: usize,
}

impl GraphText {
    /// Loads `t.files.onnx` in its fastest form (module doc); `probe` (a tokenized prompt)
    /// validates the real-tokens form.
    pub(crate) fn load(src: &BundleSource, t: &TextEncoderSpec, probe: Option<&TokenizedText>) -> Result<GraphText> {
        let roles = t
            .inputs
            .iter()
            .map(|i| match i.name.as_str() {
                "input_ids" => Ok(Role::Ids),
                "attention_mask" => Ok(Role::Mask),
                "token_type_ids" => Ok(Role::TypeIds),
                "position_ids" => Ok(Role::Positions),
                other => {
                    Err(Error::bundle(src.path_of(&t.files.onnx), format!("unknown text encoder input {other:?}")))
                }
            })
            .collect::<Result<Vec<_>>>()?;
        let pool_index = t.outputs.iter().position(|o| o.name == t.pool_output).ok_or_else(|| {
            Error::bundle(
                src.path_of(crate::bundle::manifest::MANIFEST_FILE),
                format!("text_encoder pool_output {:?} is not an output", t.pool_output),
            )
        })?;
        let feed = Feed { roles: &roles, out: pool_index, width: t.dim };
        let (plan, mode, fallback) = load_plan(src, t, &feed, probe)?;
        Ok(GraphText { plan, mode, fallback, roles, pool_index, width: t.dim })
    }

    /// The pooled output's states `(len, width)` for the first `len` tokens of `tok`.
    pub(crate) fn run(&self, tok: &TokenizedText, len: usize) -> Result<Vec<f32>> {
        Feed { roles: &self.roles, out: self.pool_index, width: self.width }.run(&self.plan, tok, len)
    }
}

/// What a run feeds and reads: the input roles, the pooled output's index and width.
struct Feed<'a> {
    roles: &'a [Role],
    out: usize,
    width: usize,
}

impl Feed<'_> {
    /// Runs `plan` on the first `len` tokens of `tok`; returns `(len, width)` states.
    fn run(&self, plan: &Plan, tok: &TokenizedText, len: usize) -> Result<Vec<f32>> {
        let mut inputs: Vec<Arc<Tensor>> = Vec::with_capacity(self.roles.len());
        for role in self.roles {
            let data: Vec<i64> = match role {
                Role::Ids => tok.input_ids[..len].to_vec(),
                Role::Mask => tok.attention_mask[..len].to_vec(),
                Role::TypeIds => tok.token_type_ids[..len].to_vec(),
                Role::Positions => (0..len as i64).collect(),
            };
            let tensor = Tensor::from_shape::<i64>(&[1, len], &data)
                .map_err(|e| Error::Inference(format!("text encoder input: {e:#}")))?;
            inputs.push(Arc::new(tensor));
        }
        let mut state = graph::spawn(plan, "text_encoder.onnx")?;
        let out = graph::run(&mut state, &inputs, "text_encoder.onnx")?;
        let states =
            out.get(self.out).ok_or_else(|| Error::Inference("text_encoder.onnx returned too few outputs".into()))?;
        Ok(graph::slice::<f32>(states, "text encoder states", len * self.width)?.to_vec())
    }
}

/// The encoder graph in the fastest form that applies (module doc, "Speed"), how it is fed,
/// and why a faster form was refused. Only the final fallback, [`graph::load`], reports
/// errors: a graph it refuses is refused with its usual message.
fn load_plan(
    src: &BundleSource,
    t: &TextEncoderSpec,
    feed: &Feed<'_>,
    probe: Option<&TokenizedText>,
) -> Result<(Plan, SequenceMode, Option<String>)> {
    let mut why = Vec::new();
    match guarded(|| read_proto(src, &t.files.onnx)) {
        Ok(mut proto) => {
            // Replaces the node list only once complete: a panic leaves `proto` as read.
            if let Err(e) = guarded(|| Ok(rewrite_dequant_gathers(&mut proto))) {
                why.push(format!("int8 gather rewrite: {e}"));
            }
            match probe {
                None => why.push("real tokens only: no probe prompt".into()),
                Some(probe) => match guarded(|| rewritten_plan(src, t, proto.clone(), true))
                    .and_then(|plan| check_real_tokens(&plan, feed, probe).map(|()| plan))
                {
                    Ok(plan) => return Ok((plan, SequenceMode::RealTokens, None)),
                    Err(e) => why.push(format!("real tokens only: {e}")),
                },
            }
            match guarded(|| rewritten_plan(src, t, proto, false)) {
                Ok(plan) => return Ok((plan, SequenceMode::Padded, Some(why.join("; ")))),
                Err(e) => why.push(format!("rewritten graph: {e}")),
            }
        }
        Err(e) => why.push(e),
    }
    let plan = graph::load(src, &t.files.onnx, &t.inputs, &t.outputs)?;
    Ok((plan, SequenceMode::Padded, Some(why.join("; "))))
}

/// Runs `f`, turning a panic (tract or prost on a hostile file) into an error string.
fn guarded<T>(f: impl FnOnce() -> std::result::Result<T, String>) -> std::result::Result<T, String> {
    catch_unwind(AssertUnwindSafe(f)).unwrap_or_else(|_| Err("panicked".into()))
}

/// The graph's protobuf, from disk or from the embedded bundle.
fn read_proto(src: &BundleSource, rel: &str) -> std::result::Result<pb::ModelProto, String> {
    let onnx = tract_onnx::onnx();
    match src.directory() {
        Some(_) => onnx.proto_model_for_path(src.path_of(rel)),
        None => onnx.proto_model_for_read(&mut &*src.read_file(rel).map_err(|e| e.to_string())?),
    }
    .map_err(|e| format!("reading the protobuf: {e:#}"))
}

/// The real-tokens form must give the probe's real tokens the states the padded run gives
/// them (the same graph at full length; module doc): float rounding only.
fn check_real_tokens(plan: &Plan, feed: &Feed<'_>, probe: &TokenizedText) -> std::result::Result<(), String> {
    let n = probe.attention_mask.iter().rposition(|&m| m != 0).map_or(1, |i| i + 1);
    let t = probe.input_ids.len();
    let short = feed.run(plan, probe, n).map_err(|e| e.to_string())?;
    let full = feed.run(plan, probe, t).map_err(|e| e.to_string())?;
    let scale = full[..n * feed.width].iter().fold(1f32, |m, v| m.max(v.abs()));
    let diff = short.iter().zip(&full).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    // NaN-safe: a NaN difference fails too.
    if diff <= 1e-4 * scale {
        Ok(())
    } else {
        Err(format!("probe states differ from the padded run by {diff:e} (scale {scale})"))
    }
}

/// `Gather(Mul(Cast(q), s), ids)` with `q` an int8 `(rows, width)` initializer and `s` a
/// float32 `(rows, 1)` initializer becomes `Mul(Cast(Gather(q, ids)), Gather(s, ids))`
/// (module doc). Returns how many gathers were rewritten.
fn rewrite_dequant_gathers(proto: &mut pb::ModelProto) -> usize {
    const FLOAT: i32 = 1;
    const INT8: i32 = 3;
    let Some(g) = proto.graph.as_mut() else { return 0 };
    let inits: HashMap<&str, (i32, &[i64])> =
        g.initializer.iter().map(|t| (t.name.as_str(), (t.data_type, t.dims.as_slice()))).collect();
    let producer: HashMap<&str, usize> =
        g.node.iter().enumerate().flat_map(|(i, n)| n.output.iter().map(move |o| (o.as_str(), i))).collect();
    let node = |name: &str, op: &str| producer.get(name).map(|&i| &g.node[i]).filter(|n| n.op_type == op);
    let mut nodes = Vec::with_capacity(g.node.len() + 8);
    let mut bypassed: Vec<Vec<String>> = Vec::new();
    let mut count = 0;
    for n in &g.node {
        let axis0 = n.attribute.iter().all(|a| a.name != "axis" || a.i == 0);
        let found = (n.op_type == "Gather" && n.input.len() == 2 && n.output.len() == 1 && axis0)
            .then(|| node(&n.input[0], "Mul"))
            .flatten()
            .filter(|m| m.input.len() == 2)
            .and_then(|m| {
                [(0, 1), (1, 0)].into_iter().find_map(|(x, s)| {
                    let cast = node(&m.input[x], "Cast")?;
                    let to_float = cast.attribute.iter().any(|a| a.name == "to" && a.i == i64::from(FLOAT));
                    let (qt, qdims) = *inits.get(cast.input.first()?.as_str())?;
                    let (st, sdims) = *inits.get(m.input[s].as_str())?;
                    (to_float
                        && cast.input.len() == 1
                        && qt == INT8
                        && st == FLOAT
                        && qdims.len() == 2
                        && sdims == [qdims[0], 1])
                    .then(|| {
                        (
                            cast.input[0].clone(),
                            m.input[s].clone(),
                            cast.attribute.clone(),
                            [m.output.clone(), cast.output.clone()],
                        )
                    })
                })
            });
        let Some((q, scale, cast_attr, outputs)) = found else {
            nodes.push(n.clone());
            continue;
        };
        let out = &n.output[0];
        let ids = &n.input[1];
        let make = |op: &str, inputs: [&str; 2], output: String, attribute: Vec<pb::AttributeProto>| pb::NodeProto {
            op_type: op.into(),
            name: format!("{output}__node"),
            input: inputs.iter().filter(|s| !s.is_empty()).map(|s| s.to_string()).collect(),
            output: vec![output],
            attribute,
            ..Default::default()
        };
        let (gq, gqf, gs) =
            (format!("{out}__gather_q"), format!("{out}__gather_q_f32"), format!("{out}__gather_scale"));
        nodes.push(make("Gather", [&q, ids], gq.clone(), vec![]));
        nodes.push(make("Cast", [&gq, ""], gqf.clone(), cast_attr));
        nodes.push(make("Gather", [&scale, ids], gs.clone(), vec![]));
        nodes.push(make("Mul", [&gqf, &gs], out.clone(), vec![]));
        bypassed.extend(outputs);
        count += 1;
    }
    // The bypassed dequantization (Mul, then Cast: the whole table) goes unless something
    // else still reads it.
    for outputs in &bypassed {
        let read = |o: &String| nodes.iter().any(|n| n.input.contains(o)) || g.output.iter().any(|v| &v.name == o);
        if !outputs.iter().any(read) {
            nodes.retain(|n| &n.output != outputs);
        }
    }
    g.node = nodes;
    count
}

/// Makes the Reshape targets of `[1, t, ..]` form (constants or initializers) copy axis 1
/// of their input instead (`[1, 0, ..]`); returns the names of the rewritten Reshapes.
fn generalize_reshapes(proto: &mut pb::ModelProto, t: i64) -> std::result::Result<Vec<String>, String> {
    const INT64: i32 = 7;
    let g = proto.graph.as_mut().ok_or("no graph")?;
    let mut uses: HashMap<String, usize> = HashMap::new();
    for n in &g.node {
        for i in &n.input {
            *uses.entry(i.clone()).or_default() += 1;
        }
    }
    let reshapes: Vec<(String, String, bool)> = g
        .node
        .iter()
        .filter(|n| n.op_type == "Reshape" && n.input.len() == 2)
        .map(|n| (n.name.clone(), n.input[1].clone(), n.attribute.iter().any(|a| a.name == "allowzero" && a.i != 0)))
        .collect();
    let values = |tp: &pb::TensorProto| -> Option<Vec<i64>> {
        if tp.data_type != INT64 || tp.dims.len() != 1 {
            return None;
        }
        if !tp.int64_data.is_empty() {
            return Some(tp.int64_data.clone());
        }
        tp.raw_data
            .len()
            .is_multiple_of(8)
            .then(|| tp.raw_data.chunks_exact(8).map(|c| i64::from_le_bytes(c.try_into().unwrap_or([0; 8]))).collect())
    };
    let mut names = Vec::new();
    for (name, shape, allowzero) in reshapes {
        let konst = g
            .node
            .iter_mut()
            .find(|n| n.op_type == "Constant" && n.output.first() == Some(&shape))
            .and_then(|n| n.attribute.iter_mut().find(|a| a.name == "value"))
            .and_then(|a| a.t.as_mut());
        let tp = match konst {
            Some(tp) => tp,
            None => match g.initializer.iter_mut().find(|i| i.name == shape) {
                Some(tp) => tp,
                None => continue, // computed in the graph: already follows the input
            },
        };
        let Some(mut v) = values(tp) else { continue };
        if v.len() < 2 || v[0] != 1 || v[1] != t {
            continue;
        }
        if allowzero || uses.get(&shape) != Some(&1) || name.is_empty() {
            return Err(format!("Reshape {name:?}: its target cannot be rewritten"));
        }
        v[1] = 0;
        tp.int64_data = v;
        tp.raw_data.clear();
        names.push(name);
    }
    Ok(names)
}

/// The graph from `proto`, checked against the manifest like [`graph::load`] does; with
/// `real_tokens`, with a symbolic sequence axis `S` (module doc).
fn rewritten_plan(
    src: &BundleSource,
    t: &TextEncoderSpec,
    mut proto: pb::ModelProto,
    real_tokens: bool,
) -> std::result::Result<Plan, String> {
    let tract = |e: tract_onnx::prelude::TractError| format!("{e:#}");
    let max = t.max_tokens;
    let reshapes = if real_tokens { generalize_reshapes(&mut proto, max as i64)? } else { Vec::new() };
    let dir = src.directory().and_then(|d| d.to_str()).map(str::to_owned);
    let onnx = tract_onnx::onnx().with_ignore_output_shapes(real_tokens).with_ignore_value_info(real_tokens);
    let parsed = onnx.parse(&proto, dir.as_deref()).map_err(tract)?;
    if !parsed.unresolved_inputs.is_empty() {
        return Err(format!("unresolved inputs {:?}", parsed.unresolved_inputs));
    }
    let mut model = parsed.model;
    drop(proto);
    let in_names: Vec<String> =
        model.input_outlets().map_err(tract)?.iter().map(|o| model.node(o.node).name.clone()).collect();
    let out_names: Vec<String> = model
        .output_outlets()
        .map_err(tract)?
        .iter()
        .map(|o| model.outlet_label(*o).unwrap_or(model.node(o.node).name.as_str()).to_string())
        .collect();
    if in_names.iter().ne(t.inputs.iter().map(|s| &s.name)) || out_names.iter().ne(t.outputs.iter().map(|s| &s.name)) {
        return Err("inputs or outputs differ from the manifest".into());
    }
    let s = model.sym("S");
    let i64t = DatumType::I64;
    for (i, spec) in t.inputs.iter().enumerate() {
        let fact = model.input_fact(i).map_err(tract)?;
        let declared = fact.shape.as_concrete_finite().map_err(tract)?;
        if spec.dtype != Dtype::Int64
            || spec.shape != [1, max]
            || fact.datum_type.concretize() != Some(i64t)
            || declared.as_deref() != Some(&[1, max][..])
        {
            return Err(format!("input {} is not int64 [1, {max}]", spec.name));
        }
        if real_tokens {
            let fact = InferenceFact::dt_shape(i64t, [1.to_dim(), s.to_dim()]);
            model.set_input_fact(i, fact).map_err(tract)?;
        }
    }
    if real_tokens {
        model.analyse(false).map_err(tract)?;
        for name in &reshapes {
            let id = model.node_by_name(name).map_err(tract)?.id;
            let facts = model.node_input_facts(id).map_err(tract)?;
            let axis1 = facts.first().and_then(|f| f.shape.dims().nth(1)).and_then(|d| d.concretize());
            if axis1 != Some(s.to_dim()) {
                return Err(format!("Reshape {name:?}: axis 1 of its input is {axis1:?}, not the sequence"));
            }
        }
    }
    let typed = model.into_typed().map_err(tract)?;
    for (i, spec) in t.outputs.iter().enumerate() {
        let fact = typed.output_fact(i).map_err(tract)?;
        let want: TVec<TDim> = spec
            .shape
            .iter()
            .enumerate()
            .map(|(k, &d)| if real_tokens && k == 1 { s.to_dim() } else { d.to_dim() })
            .collect();
        if spec.dtype != Dtype::Float32
            || spec.shape.len() != 3
            || spec.shape[1] != max
            || fact.datum_type != DatumType::F32
            || fact.shape.dims() != &*want
        {
            return Err(format!("output {} is {fact:?}, expected float32 {want:?}", spec.name));
        }
    }
    typed.into_optimized().and_then(|m| m.into_runnable()).map_err(tract)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::text::test_support::{bundles, max_abs, PROMPTS};
    use crate::model::text::{load_tokenizer, tokenize_with, TextBackend, TextEncoder};

    #[test]
    fn real_tokens_form_matches_the_exported_graph() {
        for (src, m) in bundles() {
            let t = &m.text_encoder;
            let enc = TextEncoder::load_with(&src, &m, TextBackend::Tract).unwrap();
            assert_eq!(enc.sequence_mode(), SequenceMode::RealTokens, "{:?}: {:?}", src.root(), enc.fallback_reason());
            assert!(enc.fallback_reason().is_none());
            // The file as exported, loaded as before this rewrite, run on all positions.
            let reference = graph::load(&src, &t.files.onnx, &t.inputs, &t.outputs).unwrap();
            let roles = [Role::Ids, Role::Mask, Role::TypeIds, Role::Positions];
            let feed = Feed { roles: &roles[..t.inputs.len()], out: 0, width: t.dim };
            let w = t.dim;
            for prompt in PROMPTS {
                let (tok, fast) = enc.token_states(prompt).unwrap();
                let full = feed.run(&reference, &tok, t.max_tokens).unwrap();
                let n = tok.attention_mask.iter().filter(|&&x| x != 0).count();
                let d_states = max_abs(&fast[..n * w], &full[..n * w]);
                assert!(d_states <= 1e-4, "{prompt:?}: real-token states differ by {d_states:e}");
                assert!(fast[n * w..].iter().all(|&v| v == 0.0), "padding rows are not computed");
                let got = enc.embed(prompt).unwrap();
                let want = enc.pool(&full, &tok).unwrap();
                let d = max_abs(&got, &want);
                assert!(d <= 1e-6, "{prompt:?}: embedding differs by {d:e}");
                println!("{:?} {prompt:?}: {n} tokens, states {d_states:.2e}, embedding {d:.2e}", src.root());
            }
        }
    }

    #[test]
    fn without_a_probe_the_graph_runs_padded() {
        let (src, m) = bundles().into_iter().next().unwrap();
        let t = &m.text_encoder;
        let roles = [Role::Ids, Role::Mask, Role::TypeIds, Role::Positions];
        let feed = Feed { roles: &roles[..t.inputs.len()], out: 0, width: t.dim };
        let (_, mode, why) = load_plan(&src, t, &feed, None).unwrap();
        assert_eq!(mode, SequenceMode::Padded);
        assert!(why.unwrap().contains("no probe"));
    }

    #[test]
    fn int8_gather_rewrite_is_bit_exact() {
        for (src, m) in bundles() {
            let t = &m.text_encoder;
            let mut proto = read_proto(&src, &t.files.onnx).unwrap();
            let n_nodes = proto.graph.as_ref().unwrap().node.len();
            let rewritten = rewrite_dequant_gathers(&mut proto);
            // Each Gather, Mul and Cast became Gather, Cast, Gather, Mul: the table's
            // dequantization is gone.
            assert_eq!(proto.graph.as_ref().unwrap().node.len(), n_nodes + rewritten);
            // The default bundle stores its word and position tables as int8.
            if src.root().ends_with("models/default") {
                assert_eq!(rewritten, 2);
            }
            if rewritten == 0 {
                continue;
            }
            let plan = rewritten_plan(&src, t, proto, false).unwrap();
            let reference = graph::load(&src, &t.files.onnx, &t.inputs, &t.outputs).unwrap();
            let tokenizer = load_tokenizer(
                &src.path_of(&t.files.tokenizer),
                &src.read_file(&t.files.tokenizer).unwrap(),
                t.max_tokens,
            )
            .unwrap();
            let roles = [Role::Ids, Role::Mask, Role::TypeIds, Role::Positions];
            let feed = Feed { roles: &roles[..t.inputs.len()], out: 0, width: t.outputs[0].shape[2] };
            for prompt in PROMPTS {
                let tok = tokenize_with(&tokenizer, t.max_tokens, prompt).unwrap();
                let a = feed.run(&plan, &tok, t.max_tokens).unwrap();
                let b = feed.run(&reference, &tok, t.max_tokens).unwrap();
                assert!(
                    a == b,
                    "{prompt:?}: {rewritten} int8 gathers rewritten, states differ by {:e}",
                    max_abs(&a, &b)
                );
            }
        }
    }

    #[test]
    fn reshape_targets_are_rewritten_only_when_safe() {
        use pb::{AttributeProto, GraphProto, ModelProto, NodeProto, TensorProto};
        let konst = |name: &str, v: Vec<i64>| NodeProto {
            op_type: "Constant".into(),
            output: vec![name.into()],
            attribute: vec![AttributeProto {
                name: "value".into(),
                t: Some(TensorProto { dims: vec![v.len() as i64], data_type: 7, int64_data: v, ..Default::default() }),
                ..Default::default()
            }],
            ..Default::default()
        };
        let reshape = |name: &str, shape: &str, allowzero: i64| NodeProto {
            op_type: "Reshape".into(),
            name: name.into(),
            input: vec!["x".into(), shape.into()],
            output: vec![format!("{name}_out")],
            attribute: vec![AttributeProto { name: "allowzero".into(), i: allowzero, ..Default::default() }],
            ..Default::default()
        };
        let model = |nodes: Vec<NodeProto>| ModelProto {
            graph: Some(GraphProto { node: nodes, ..Default::default() }),
            ..Default::default()
        };
        let target = |p: &ModelProto, k: usize| {
            p.graph.as_ref().unwrap().node[k].attribute[0].t.as_ref().unwrap().int64_data.clone()
        };
        let mut p = model(vec![
            konst("a", vec![1, 8, -1, 8]),
            konst("b", vec![1, 4, -1]),
            konst("c", vec![8, -1]),
            reshape("r1", "a", 0),
            reshape("r2", "b", 0),
            reshape("r3", "c", 0),
        ]);
        assert_eq!(generalize_reshapes(&mut p, 8).unwrap(), vec!["r1".to_string()]);
        assert_eq!(target(&p, 0), vec![1, 0, -1, 8]);
        assert_eq!(target(&p, 1), vec![1, 4, -1]);
        // allowzero makes 0 a literal size; a shared target would change another node.
        let mut p = model(vec![konst("a", vec![1, 8, -1]), reshape("r1", "a", 1)]);
        assert!(generalize_reshapes(&mut p, 8).is_err());
        let mut p = model(vec![konst("a", vec![1, 8, -1]), reshape("r1", "a", 0), reshape("r2", "a", 0)]);
        assert!(generalize_reshapes(&mut p, 8).is_err());
    }
}
