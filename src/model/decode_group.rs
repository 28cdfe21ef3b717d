//! How many tokens a stream decodes at once after its first chunk.
//!
//! A decode of one token reads all of the decoder's weights for very few positions (1 at
//! the token rate, 2 and 4 at the first frame rates), so those layers are memory-bound:
//! the default bundle's decoder reads 19 MB of int8 weights per token. The decoder is
//! causal and the native one computes only new positions, so it can take G consecutive
//! tokens in one pass (`DecoderModel::decode_group`): every layer then has G times the
//! positions and each weight is read once per G tokens, with the same bits as G decodes.
//! The cost is latency the host never sees: token k's frames wait for steps k+1..k+G-1
//! (a fraction of a millisecond each against the 0.53 s of motion a chunk holds); the
//! first chunk is always decoded alone, so the time to first frame does not change.
//!
//! Default: 4 when the decoder is native and the step reads no more weights per token
//! than the decoder (the default bundle: 10 MB against 19 MB). Measured on the 2-core
//! machine (five interleaved rounds of `comgrasp bench --bundle models/default`), the
//! stream's median real-time factor went 203x (1) -> 269x (4) -> 306x (8) (docs/performance.md
//! has the final binary's numbers). 4, not 8, because a cancel or
//! `cg_stream_destroy` waits for the call in progress (a G-token decode and G steps): ~8 ms
//! at 4 and ~14 ms at 8 here (G x the median time per token), up to a whole frame of a
//! 60 Hz game at 8. Otherwise 1: tract's graph decodes one token per run (nothing to
//! gain), and a step much bigger than the decoder (the paper model's 1.8 GB) dominates each
//! token, so grouping would gain little while a call would take G of those steps.
//! `RuntimeOptions::decode_group` (1..=8) overrides.
use super::{DecoderModel, StepModel, MAX_DECODE_GROUP};

/// The default group when it pays (module doc).
const DEFAULT_GROUP: usize = 4;

/// Tokens in the decode that starts at step `k` of a stream decoding `group` at once: the
/// first token alone (so the time to first frame waits for no group), then `group`.
pub fn tokens_at(k: usize, group: usize) -> usize {
    if k == 0 {
        1
    } else {
        group
    }
}

/// Tokens per decode for these models: `option` (`RuntimeOptions::decode_group`, clamped
/// to 1 ..= [`MAX_DECODE_GROUP`]) when set, else the module doc's rule.
pub fn tokens_per_decode(step: &StepModel, decoder: &DecoderModel, option: Option<usize>) -> usize {
    if let Some(g) = option {
        return g.clamp(1, MAX_DECODE_GROUP);
    }
    let pays = match (step.native_weight_bytes(), decoder.native_threads_and_bytes()) {
        (Some(step_bytes), Some((_, decoder_bytes))) => step_bytes <= decoder_bytes,
        _ => false,
    };
    if pays {
        DEFAULT_GROUP
    } else {
        1
    }
}
