//! Loading one ONNX graph of a bundle into tract, and the small tensor helpers the
//! runners share.
//!
//! Every graph is checked against the manifest's `inputs`/`outputs` lists (names, order,
//! dtypes, static shapes) as tract itself sees them, so a graph that disagrees with its
//! manifest is a load-time `Error::Bundle`, never a wrong-shape failure mid-stream. The
//! graphs are static (DESIGN §4): the shapes come from the ONNX file and are required to
//! be concrete; nothing is left symbolic for tract to resolve per call.
//!
//! tract is third-party code fed with files from disk: loading and running are wrapped in
//! `catch_unwind` so a panic inside it becomes an error value.
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::sync::Arc;

use tract_onnx::prelude::*;

use crate::bundle::manifest::{Dtype, IoSpec};
use crate::bundle::BundleSource;
use crate::error::{Error, Result};

/// A loaded, optimized graph, shared by every stream.
pub(crate) type Plan = Arc<TypedSimplePlan>;
/// Per-stream run state of a [`Plan`] (keeps tract's scratch between calls).
pub(crate) type PlanState = TypedSimpleState;

fn datum(d: Dtype) -> DatumType {
    match d {
        Dtype::Int64 => i64::datum_type(),
        Dtype::Float32 => f32::datum_type(),
    }
}

/// `float32 [1, 34]`, in the manifest's words where possible.
fn describe(fact: &TypedFact) -> String {
    let dt = if fact.datum_type == f32::datum_type() {
        "float32".to_string()
    } else if fact.datum_type == i64::datum_type() {
        "int64".to_string()
    } else {
        format!("{:?}", fact.datum_type)
    };
    match fact.shape.as_concrete() {
        Some(s) => format!("{dt} {s:?}"),
        None => format!("{dt} {:?} (not static)", fact.shape),
    }
}

/// Loads the graph `rel` of the bundle with tract, checks its inputs and outputs against
/// the manifest's lists, optimizes it and makes it runnable.
pub(crate) fn load(src: &BundleSource, rel: &str, inputs: &[IoSpec], outputs: &[IoSpec]) -> Result<Plan> {
    let path = src.path_of(rel);
    if src.omits(rel) {
        return Err(Error::bundle(
            &path,
            "the embedded default bundle holds only the native weights of this model, not its ONNX graph; \
             for the tract backend load the bundle directory (models/default of the source tree)",
        ));
    }
    match catch_unwind(AssertUnwindSafe(|| load_inner(src, rel, &path, inputs, outputs))) {
        Ok(r) => r,
        Err(p) => {
            Err(Error::bundle(&path, format!("tract panicked while loading the graph: {}", panic_text(p.as_ref()))))
        }
    }
}

/// Reads the graph `rel` with tract and checks its inputs and outputs against the manifest,
/// without optimizing it: for a graph the native path runs instead (the file stays the
/// reference and must still match its manifest). A graph the source leaves out (the
/// embedded default's) has nothing to check: the same bytes were checked in the directory
/// it was built from (`tests/embedded_default.rs`).
pub(crate) fn check(src: &BundleSource, rel: &str, inputs: &[IoSpec], outputs: &[IoSpec]) -> Result<()> {
    if src.omits(rel) {
        return Ok(());
    }
    let path = src.path_of(rel);
    match catch_unwind(AssertUnwindSafe(|| typed(src, rel, &path, inputs, outputs).map(drop))) {
        Ok(r) => r,
        Err(p) => {
            Err(Error::bundle(&path, format!("tract panicked while loading the graph: {}", panic_text(p.as_ref()))))
        }
    }
}

fn load_inner(src: &BundleSource, rel: &str, path: &Path, inputs: &[IoSpec], outputs: &[IoSpec]) -> Result<Plan> {
    let typed = typed(src, rel, path, inputs, outputs)?;
    let plan = typed
        .into_optimized()
        .and_then(|m| m.into_runnable())
        .map_err(|e| Error::bundle(path, format!("tract cannot optimize the graph: {e:#}")))?;
    Ok(plan)
}

fn typed(src: &BundleSource, rel: &str, path: &Path, inputs: &[IoSpec], outputs: &[IoSpec]) -> Result<TypedModel> {
    let bad = |msg: String| Error::bundle(path, msg);
    let model = match src.directory() {
        // From disk tract maps the file and resolves ONNX external data beside it.
        Some(_) => tract_onnx::onnx().model_for_path(path),
        // From memory there is no directory, so a graph with external data fails here with
        // tract's "external data was detected" message.
        None => tract_onnx::onnx().model_for_read(&mut &*src.read_file(rel)?),
    }
    .map_err(|e| bad(format!("tract cannot read the ONNX graph: {e:#}")))?;

    // Names and order, as the ONNX file declares them.
    let in_names: Vec<String> = model
        .input_outlets()
        .map_err(|e| bad(format!("{e:#}")))?
        .iter()
        .map(|o| model.node(o.node).name.clone())
        .collect();
    let out_names: Vec<String> = model
        .output_outlets()
        .map_err(|e| bad(format!("{e:#}")))?
        .iter()
        .map(|o| model.outlet_label(*o).unwrap_or(model.node(o.node).name.as_str()).to_string())
        .collect();
    let want_in: Vec<&str> = inputs.iter().map(|s| s.name.as_str()).collect();
    let want_out: Vec<&str> = outputs.iter().map(|s| s.name.as_str()).collect();
    if in_names != want_in {
        return Err(bad(format!("graph inputs are {in_names:?}, the manifest declares {want_in:?}")));
    }
    if out_names != want_out {
        return Err(bad(format!("graph outputs are {out_names:?}, the manifest declares {want_out:?}")));
    }

    // Dtypes and shapes, as tract types them.
    let typed = model.into_typed().map_err(|e| bad(format!("tract cannot type the graph: {e:#}")))?;
    for (i, spec) in inputs.iter().enumerate() {
        let fact = typed.input_fact(i).map_err(|e| bad(format!("{e:#}")))?;
        check_fact(path, "input", spec, fact)?;
    }
    for (i, spec) in outputs.iter().enumerate() {
        let fact = typed.output_fact(i).map_err(|e| bad(format!("{e:#}")))?;
        check_fact(path, "output", spec, fact)?;
    }
    Ok(typed)
}

fn check_fact(path: &Path, kind: &str, spec: &IoSpec, fact: &TypedFact) -> Result<()> {
    let shape_ok = fact.shape.as_concrete() == Some(spec.shape.as_slice());
    if fact.datum_type != datum(spec.dtype) || !shape_ok {
        return Err(Error::bundle(
            path,
            format!(
                "{kind} {} is {} in the graph (as typed by tract), the manifest declares {} {:?}",
                spec.name,
                describe(fact),
                spec.dtype,
                spec.shape
            ),
        ));
    }
    Ok(())
}

/// A zero-filled tensor of the declared dtype and shape (the reusable input buffers).
pub(crate) fn zeros(spec: &IoSpec) -> Result<Arc<Tensor>> {
    let t = match spec.dtype {
        Dtype::Int64 => Tensor::zero::<i64>(&spec.shape),
        Dtype::Float32 => Tensor::zero::<f32>(&spec.shape),
    };
    t.map(Arc::new).map_err(|e| Error::Inference(format!("allocating {}: {e:#}", spec.name)))
}

/// Mutable access to a reusable input buffer. After a run tract has dropped its
/// references, so this is normally the buffer itself; if tract kept one, the buffer is
/// copied first (correct, only slower).
pub(crate) fn slice_mut<'a, T: Datum>(t: &'a mut Arc<Tensor>, what: &str) -> Result<&'a mut [T]> {
    Arc::make_mut(t)
        .to_plain_array_view_mut::<T>()
        .map_err(|e| Error::Inference(format!("{what}: {e:#}")))?
        .into_slice()
        .ok_or_else(|| Error::Inference(format!("{what}: tensor is not contiguous")))
}

/// Zero-fills a reusable input buffer (f32 or i64).
pub(crate) fn fill_zero(t: &mut Arc<Tensor>) -> Result<()> {
    let dt = t.datum_type();
    if dt == f32::datum_type() {
        slice_mut::<f32>(t, "buffer")?.fill(0.0);
    } else if dt == i64::datum_type() {
        slice_mut::<i64>(t, "buffer")?.fill(0);
    } else {
        return Err(Error::Inference(format!("cannot zero a {dt:?} buffer")));
    }
    Ok(())
}

/// Read access to an output tensor's elements, checking its dtype and length.
pub(crate) fn slice<'a, T: Datum>(t: &'a Tensor, what: &str, len: usize) -> Result<&'a [T]> {
    let s =
        t.try_as_plain_ram().and_then(|v| v.as_slice::<T>()).map_err(|e| Error::Inference(format!("{what}: {e:#}")))?;
    if s.len() != len {
        return Err(Error::Inference(format!("{what}: {} values, expected {len}", s.len())));
    }
    Ok(s)
}

/// Runs `state` on `inputs` (cheap Arc clones of the caller's buffers), turning errors
/// and panics into `Error::Inference`.
pub(crate) fn run(state: &mut PlanState, inputs: &[Arc<Tensor>], what: &str) -> Result<TVec<TValue>> {
    let values: TVec<TValue> = inputs.iter().map(|t| TValue::from_const(Arc::clone(t))).collect();
    match catch_unwind(AssertUnwindSafe(|| state.run(values))) {
        Ok(Ok(out)) => Ok(out),
        Ok(Err(e)) => Err(Error::Inference(format!("{what}: {e:#}"))),
        Err(p) => Err(Error::Inference(format!("{what}: tract panicked: {}", panic_text(p.as_ref())))),
    }
}

/// A new run state for `plan`.
pub(crate) fn spawn(plan: &Plan, what: &str) -> Result<PlanState> {
    plan.spawn().map_err(|e| Error::Inference(format!("{what}: cannot create a run state: {e:#}")))
}

fn panic_text(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}
