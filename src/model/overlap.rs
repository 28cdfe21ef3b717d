//! Decoding token k's chunk while token step k+1 runs (one stream, two threads).
//!
//! The decode of chunk k needs only step k's codes and the decoder context; step k+1 needs
//! only those codes and the KV cache. So a stream can run them at once: the native
//! decoder hands out its four components and the step as five jobs to its two threads
//! (longest first, each thread taking the next as it gets free), and the step runs on one
//! thread instead of its own two-thread team. One hand-over per token instead of two, and
//! no core idles while the other finishes its share. Results are bit-identical either way
//! (every job runs on one thread, as it would alone).
//!
//! It pays when the step is no bigger than the decoder (the default bundle: 10 MB of step
//! weights, 19 MB of decoder weights); a step much bigger than the decoder (the paper
//! model's 1.8 GB) is faster on its own team, one after the other. `COMGRASP_OVERLAP=0|1`
//! overrides the choice.
use super::{DecoderModel, DecoderState, StepModel, StepState};
use crate::bundle::N_STREAMS;
use crate::error::{Error, Result};

/// Environment variable: `1` overlaps whenever both models are native and the decoder has
/// a second thread, `0` never (read once per engine).
pub const OVERLAP_ENV: &str = "COMGRASP_OVERLAP";

/// Whether [`decode_and_step`] should overlap for these models (`COMGRASP_OVERLAP`, else the
/// rule of the module doc).
pub fn overlaps(step: &StepModel, decoder: &DecoderModel) -> Result<bool> {
    let possible = match (step.native_weight_bytes(), decoder.native_threads_and_bytes()) {
        (Some(step_bytes), Some((2, decoder_bytes))) => Some(step_bytes <= decoder_bytes),
        _ => None,
    };
    match std::env::var(OVERLAP_ENV).as_deref() {
        Ok("0") => Ok(false),
        Ok("1") => Ok(possible.is_some()),
        Ok("") | Err(std::env::VarError::NotPresent) => Ok(possible.unwrap_or(false)),
        Ok(v) => Err(Error::InvalidArgument(format!("{OVERLAP_ENV}={v:?}: expected 0 or 1"))),
        Err(e) => Err(Error::InvalidArgument(format!("{OVERLAP_ENV}: {e}"))),
    }
}

/// `decoder.decode_group(dstate, codes, out)` and then `step.step(sstate, last, pos,
/// text_emb)` where `last` is the last of `codes`, with the same results and errors; the
/// two run at once when `overlap` (see [`overlaps`]). Nothing is changed if an argument is
/// invalid. Allocation-free on the native path.
#[allow(clippy::too_many_arguments)]
pub fn decode_and_step<'s>(
    decoder: &DecoderModel, dstate: &mut DecoderState, codes: &[[i64; N_STREAMS]], out: &mut [f32],
    step: &StepModel, sstate: &'s mut StepState, pos: usize, text_emb: &[f32], overlap: bool,
) -> Result<[&'s [f32]; N_STREAMS]> {
    decoder.check(dstate, codes, out)?;
    let last = *codes.last().ok_or_else(|| Error::InvalidArgument("no codes to decode".into()))?;
    step.check(sstate, last, pos, text_emb)?;
    if overlap {
        let mut stepped = Ok(());
        let mut job = || stepped = step.run_checked(sstate, last, pos, text_emb, true);
        decoder.decode_checked(dstate, codes, out, Some(&mut job))?;
        stepped?;
    } else {
        decoder.decode_checked(dstate, codes, out, None)?;
        step.run_checked(sstate, last, pos, text_emb, false)?;
    }
    Ok(sstate.logits())
}
