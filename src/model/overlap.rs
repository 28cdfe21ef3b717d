//! Decoding a group of tokens while the next token steps run (one stream, two threads).
//!
//! The decode of chunk k needs only step k's codes and the decoder context; step k+1 needs
//! only those codes and the KV cache. So a stream can run them at once: the native
//! decoder hands out its four components and the steps as five jobs to its two threads
//! (longest first, each thread taking the next as it gets free), and the steps run on one
//! thread instead of their own two-thread team. [`decode_and_step`] runs one step with a
//! decode; [`decode_and_steps`] runs the next decode group's steps (sampling each, so each
//! step has its input) while this group decodes, so with decode groups no step waits for
//! a decode or a decode for a step. Results are bit-identical either way (every job runs
//! on one thread, as it would alone).
//!
//! It pays when the step is no bigger than the decoder (the default bundle: 10 MB of step
//! weights, 19 MB of decoder weights); a step much bigger than the decoder (the paper
//! model's 1.8 GB) is faster on its own team, one after the other.
//! `RuntimeOptions::overlap` overrides the choice.
use super::{DecoderModel, DecoderState, StepModel, StepState};
use crate::bundle::N_STREAMS;
use crate::error::{Error, Result};

/// Whether [`decode_and_step`] should overlap for these models: `option`
/// (`RuntimeOptions::overlap`: `Some(true)` whenever both models are native and the decoder
/// has a second thread, `Some(false)` never), else the rule of the module doc.
pub fn overlaps(step: &StepModel, decoder: &DecoderModel, option: Option<bool>) -> bool {
    let possible = match (step.native_weight_bytes(), decoder.native_threads_and_bytes()) {
        (Some(step_bytes), Some((2, decoder_bytes))) => Some(step_bytes <= decoder_bytes),
        _ => None,
    };
    match option {
        Some(on) => on && possible.is_some(),
        None => possible.unwrap_or(false),
    }
}

/// `decoder.decode_group(dstate, codes, out)` and then `step.step(sstate, last, pos,
/// text_emb)` where `last` is the last of `codes`, with the same results and errors; the
/// two run at once when `overlap` (see [`overlaps`]). Nothing is changed if an argument is
/// invalid. Allocation-free on the native path.
#[allow(clippy::too_many_arguments)]
pub fn decode_and_step<'s>(
    decoder: &DecoderModel,
    dstate: &mut DecoderState,
    codes: &[[i64; N_STREAMS]],
    out: &mut [f32],
    step: &StepModel,
    sstate: &'s mut StepState,
    pos: usize,
    text_emb: &[f32],
    overlap: bool,
) -> Result<[&'s [f32]; N_STREAMS]> {
    let last = check(decoder, dstate, codes, out, step, sstate, pos, text_emb)?;
    let mut stepped = Ok(());
    let mut job = || stepped = step.run_checked(sstate, last, pos, text_emb, overlap);
    decode_with(decoder, dstate, codes, out, &mut job, overlap)?;
    stepped?;
    Ok(sstate.logits())
}

/// [`decode_and_step`] with the steps of the *next* decode group: `decoder.decode_group(
/// dstate, codes, out)` while one thread runs up to `ahead.len()` token steps from `pos` on,
/// each on the codes of the step before (the first on the last of `codes`), each sampled by
/// `sample(pos, logits)`: `Some(codes)` go into `ahead`, `None` (End) stops. Returns how
/// many codes `ahead` got and whether End stopped them. Nothing is changed if an argument
/// is invalid; a sampling error is returned after the decode.
#[allow(clippy::too_many_arguments)]
pub fn decode_and_steps<F>(
    decoder: &DecoderModel,
    dstate: &mut DecoderState,
    codes: &[[i64; N_STREAMS]],
    out: &mut [f32],
    step: &StepModel,
    sstate: &mut StepState,
    pos: usize,
    text_emb: &[f32],
    ahead: &mut [[i64; N_STREAMS]],
    mut sample: F,
    overlap: bool,
) -> Result<(usize, bool)>
where
    F: FnMut(usize, [&[f32]; N_STREAMS]) -> Result<Option<[i64; N_STREAMS]>> + Send,
{
    let mut prev = check(decoder, dstate, codes, out, step, sstate, pos, text_emb)?;
    let mut stepped = Ok((0, false));
    let mut job = || {
        stepped = (|| {
            for (i, slot) in ahead.iter_mut().enumerate() {
                let p = pos + i;
                if i > 0 {
                    // later inputs are sampled codes; the first was checked above
                    step.check(sstate, prev, p, text_emb)?;
                }
                step.run_checked(sstate, prev, p, text_emb, overlap)?;
                match sample(p, sstate.logits())? {
                    Some(c) => {
                        *slot = c;
                        prev = c;
                    }
                    None => return Ok((i, true)),
                }
            }
            Ok((ahead.len(), false))
        })()
    };
    decode_with(decoder, dstate, codes, out, &mut job, overlap)?;
    stepped
}

/// The checks of both calls, before either changes a state; the step's input codes.
#[allow(clippy::too_many_arguments)]
fn check(
    decoder: &DecoderModel,
    dstate: &DecoderState,
    codes: &[[i64; N_STREAMS]],
    out: &[f32],
    step: &StepModel,
    sstate: &StepState,
    pos: usize,
    text_emb: &[f32],
) -> Result<[i64; N_STREAMS]> {
    decoder.check(dstate, codes, out)?;
    let last = *codes.last().ok_or_else(|| Error::InvalidArgument("no codes to decode".into()))?;
    step.check(sstate, last, pos, text_emb)?;
    Ok(last)
}

/// The decode, with `job` as one more job of the decoder's threads when `overlap` (run on
/// one thread), else after it.
fn decode_with(
    decoder: &DecoderModel,
    dstate: &mut DecoderState,
    codes: &[[i64; N_STREAMS]],
    out: &mut [f32],
    job: &mut (dyn FnMut() + Send),
    overlap: bool,
) -> Result<()> {
    if overlap {
        decoder.decode_checked(dstate, codes, out, Some(job), true)
    } else {
        decoder.decode_checked(dstate, codes, out, None, true)?;
        job();
        Ok(())
    }
}
