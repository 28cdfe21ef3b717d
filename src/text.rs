//! Text -> one sentence embedding: the bundle's `tokenizer.json` (Hugging Face `tokenizers`
//! 0.22) and `text_encoder.onnx` (token states only), pooled and L2-normalized here.
//!
//! Pooling lives in Rust, not in the graph, because a pooling/normalize tail exported into
//! ONNX gave wrong embeddings in tract (DESIGN §4). The rule is the Python one
//! (`comgrasp_train.text_encoder.pool_token_states`), with the manifest's eps values:
//! * mean: `e = Σ_t m_t h_t / max(Σ_t m_t, mean_eps)` over the attention mask;
//! * eos: `e = h[i]` with `i` the first `eos_id` token (`first_eos`) or the first position
//!   of the largest id (`argmax_id`);
//! * then, if `normalize`, `e / max(‖e‖₂, norm_eps)`.
//!
//! Sums are accumulated in f64 (PyTorch sums f32 in another order; f64 keeps the Rust
//! result within rounding of the exact value, well inside the 1e-5 parity tolerance).
//!
//! Text handling: empty (or whitespace-only) text is an error; text longer than
//! [`MAX_TEXT_BYTES`] bytes is an error (it cannot be meaningful for a prompt and bounds
//! the tokenizer's work); anything shorter is tokenized with the truncation and fixed
//! padding written into tokenizer.json, so a prompt with more than `max_tokens` tokens
//! is truncated (keeping the final special token) and [`TextEmbedding::truncated`] says so.
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::sync::Arc;

use tokenizers::Tokenizer;
use tract_onnx::prelude::Tensor;

use crate::bundle::manifest::{EosSelection, Manifest, Pooling};
use crate::bundle::BundleSource;
use crate::error::{Error, Result};
use crate::model::graph::{self, Plan};

/// Longest prompt accepted, in UTF-8 bytes.
pub const MAX_TEXT_BYTES: usize = 4096;

/// What each graph input carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Role {
    Ids,
    Mask,
    TypeIds,
    Positions,
}

/// The tokenizer's output for one prompt, padded to `max_tokens`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TokenizedText {
    pub input_ids: Vec<i64>,
    pub attention_mask: Vec<i64>,
    pub token_type_ids: Vec<i64>,
    /// The prompt had more tokens than fit and was cut.
    pub truncated: bool,
}

/// An embedding and how it was obtained.
#[derive(Clone, Debug, PartialEq)]
pub struct TextEmbedding {
    /// `dim` values, L2-normalized when the manifest says so.
    pub embedding: Vec<f32>,
    /// The prompt was truncated to `max_tokens` tokens.
    pub truncated: bool,
    /// Real (non-padding) tokens fed to the encoder, special tokens included.
    pub n_tokens: usize,
}

/// Tokenizer + encoder graph + pooling rule; shared by all streams (`Send + Sync`).
pub struct TextEncoder {
    tokenizer: Tokenizer,
    plan: Plan,
    roles: Vec<Role>,
    /// Index of `pool_output` among the graph outputs, and its width.
    pool_index: usize,
    width: usize,
    max_tokens: usize,
    pooling: Pooling,
    eos_id: Option<i64>,
    eos_selection: Option<EosSelection>,
    normalize: bool,
    mean_eps: f64,
    norm_eps: f64,
}

impl std::fmt::Debug for TextEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TextEncoder").field("max_tokens", &self.max_tokens).field("dim", &self.width)
            .field("pooling", &self.pooling).field("normalize", &self.normalize).finish_non_exhaustive()
    }
}

impl TextEncoder {
    /// Loads the tokenizer and the graph named by the (verified) manifest and checks that
    /// the tokenizer pads and truncates to exactly `max_tokens`.
    pub fn load(src: &BundleSource, m: &Manifest) -> Result<TextEncoder> {
        let t = &m.text_encoder;
        let tok_path = src.path_of(&t.files.tokenizer);
        let tokenizer = load_tokenizer(&tok_path, &src.read_file(&t.files.tokenizer)?, t.max_tokens)?;
        let roles = t.inputs.iter().map(|i| match i.name.as_str() {
            "input_ids" => Ok(Role::Ids),
            "attention_mask" => Ok(Role::Mask),
            "token_type_ids" => Ok(Role::TypeIds),
            "position_ids" => Ok(Role::Positions),
            other => Err(Error::bundle(src.path_of(&t.files.onnx), format!("unknown text encoder input {other:?}"))),
        }).collect::<Result<Vec<_>>>()?;
        let pool_index = t.outputs.iter().position(|o| o.name == t.pool_output).ok_or_else(|| {
            Error::bundle(src.path_of(crate::bundle::manifest::MANIFEST_FILE),
                          format!("text_encoder pool_output {:?} is not an output", t.pool_output))
        })?;
        let plan = graph::load(src, &t.files.onnx, &t.inputs, &t.outputs)?;
        let enc = TextEncoder {
            tokenizer,
            plan,
            roles,
            pool_index,
            width: t.dim,
            max_tokens: t.max_tokens,
            pooling: t.pooling,
            eos_id: t.eos_id,
            eos_selection: t.eos_selection,
            normalize: t.normalize,
            mean_eps: t.mean_eps,
            norm_eps: t.norm_eps,
        };
        // The Python verifier's check: a short prompt comes out exactly max_tokens long.
        let probe = enc.tokenize("a test prompt").map_err(|e| Error::bundle(&tok_path, e.to_string()))?;
        if probe.input_ids.len() != t.max_tokens {
            return Err(Error::bundle(&tok_path, format!(
                "pads to {} tokens, manifest max_tokens is {}", probe.input_ids.len(), t.max_tokens)));
        }
        Ok(enc)
    }

    /// Width of the embedding.
    pub fn dim(&self) -> usize {
        self.width
    }

    /// Tokens per prompt (fixed).
    pub fn max_tokens(&self) -> usize {
        self.max_tokens
    }

    /// The embedding of `text` (see the module doc for what text is accepted).
    pub fn embed(&self, text: &str) -> Result<Vec<f32>> {
        self.encode(text).map(|e| e.embedding)
    }

    /// The embedding of `text` with the truncation flag.
    pub fn encode(&self, text: &str) -> Result<TextEmbedding> {
        let (tok, states) = self.token_states(text)?;
        let embedding = self.pool(&states, &tok)?;
        let n_tokens = tok.attention_mask.iter().filter(|&&m| m != 0).count();
        Ok(TextEmbedding { embedding, truncated: tok.truncated, n_tokens })
    }

    /// The tokenizer's output and the pooled graph output, `(max_tokens, dim)` row-major,
    /// before pooling (for parity tests and diagnostics).
    pub fn token_states(&self, text: &str) -> Result<(TokenizedText, Vec<f32>)> {
        let tok = self.tokenize(text)?;
        let t = self.max_tokens;
        let mut inputs: Vec<Arc<Tensor>> = Vec::with_capacity(self.roles.len());
        for role in &self.roles {
            let data: Vec<i64> = match role {
                Role::Ids => tok.input_ids.clone(),
                Role::Mask => tok.attention_mask.clone(),
                Role::TypeIds => tok.token_type_ids.clone(),
                Role::Positions => (0..t as i64).collect(),
            };
            let tensor = Tensor::from_shape::<i64>(&[1, t], &data)
                .map_err(|e| Error::Inference(format!("text encoder input: {e:#}")))?;
            inputs.push(Arc::new(tensor));
        }
        let mut state = graph::spawn(&self.plan, "text_encoder.onnx")?;
        let out = graph::run(&mut state, &inputs, "text_encoder.onnx")?;
        let states = out.get(self.pool_index)
            .ok_or_else(|| Error::Inference("text_encoder.onnx returned too few outputs".into()))?;
        let states = graph::slice::<f32>(states, "text encoder states", t * self.width)?.to_vec();
        Ok((tok, states))
    }

    /// Tokenizes `text` exactly as the encoder will see it.
    pub fn tokenize(&self, text: &str) -> Result<TokenizedText> {
        if text.trim().is_empty() {
            return Err(Error::InvalidArgument("text is empty".into()));
        }
        if text.len() > MAX_TEXT_BYTES {
            return Err(Error::InvalidArgument(format!(
                "text is {} bytes long, the limit is {MAX_TEXT_BYTES}", text.len())));
        }
        let enc = match catch_unwind(AssertUnwindSafe(|| self.tokenizer.encode_fast(text, true))) {
            Ok(Ok(enc)) => enc,
            Ok(Err(e)) => return Err(Error::Inference(format!("tokenizer: {e}"))),
            Err(_) => return Err(Error::Inference("tokenizer panicked".into())),
        };
        let ids = enc.get_ids();
        if ids.len() != self.max_tokens {
            return Err(Error::Inference(format!(
                "tokenizer produced {} tokens, the encoder takes exactly {}", ids.len(), self.max_tokens)));
        }
        let widen = |v: &[u32]| v.iter().map(|&x| i64::from(x)).collect::<Vec<i64>>();
        Ok(TokenizedText {
            input_ids: widen(ids),
            attention_mask: widen(enc.get_attention_mask()),
            token_type_ids: widen(enc.get_type_ids()),
            truncated: !enc.get_overflowing().is_empty(),
        })
    }

    /// Pools (T, width) token states into one embedding (module doc).
    fn pool(&self, states: &[f32], tok: &TokenizedText) -> Result<Vec<f32>> {
        let w = self.width;
        let mut e = vec![0f64; w];
        match self.pooling {
            Pooling::Mean => {
                let mut total = 0f64;
                for (t, &m) in tok.attention_mask.iter().enumerate() {
                    let m = m as f64;
                    if m != 0.0 {
                        total += m;
                        for (acc, &h) in e.iter_mut().zip(&states[t * w..(t + 1) * w]) {
                            *acc += m * f64::from(h);
                        }
                    }
                }
                let denom = total.max(self.mean_eps);
                e.iter_mut().for_each(|v| *v /= denom);
            }
            Pooling::Eos => {
                let ids = &tok.input_ids;
                let at = match self.eos_selection {
                    Some(EosSelection::ArgmaxId) => {
                        // First position of the largest id.
                        let max = ids.iter().copied().max().unwrap_or(0);
                        ids.iter().position(|&x| x == max)
                    }
                    Some(EosSelection::FirstEos) | None => {
                        let eos = self.eos_id.ok_or_else(|| Error::Inference("eos pooling without eos_id".into()))?;
                        ids.iter().position(|&x| x == eos)
                    }
                };
                let at = at.ok_or_else(|| Error::Inference("the tokenized text has no EOS token".into()))?;
                for (acc, &h) in e.iter_mut().zip(&states[at * w..(at + 1) * w]) {
                    *acc = f64::from(h);
                }
            }
        }
        if self.normalize {
            let norm = e.iter().map(|v| v * v).sum::<f64>().sqrt().max(self.norm_eps);
            e.iter_mut().for_each(|v| *v /= norm);
        }
        Ok(e.into_iter().map(|v| v as f32).collect())
    }
}

/// Parses tokenizer.json (`bytes`; `path` names it in errors) and checks its
/// padding/truncation settings against `max_tokens`.
fn load_tokenizer(path: &Path, bytes: &[u8], max_tokens: usize) -> Result<Tokenizer> {
    let tok = match catch_unwind(|| Tokenizer::from_bytes(bytes)) {
        Ok(Ok(t)) => t,
        Ok(Err(e)) => return Err(Error::bundle(path, format!("not a valid tokenizers JSON: {e}"))),
        Err(_) => return Err(Error::bundle(path, "the tokenizers crate panicked while reading it")),
    };
    use tokenizers::{PaddingDirection, PaddingStrategy, PostProcessor};
    match tok.get_padding() {
        Some(p) if matches!(p.strategy, PaddingStrategy::Fixed(n) if n == max_tokens)
            && matches!(p.direction, PaddingDirection::Right) => {}
        other => return Err(Error::bundle(path, format!(
            "padding must be Fixed({max_tokens}) to the right, the file has {other:?}"))),
    }
    match tok.get_truncation() {
        Some(t) if t.max_length == max_tokens => {}
        other => return Err(Error::bundle(path, format!(
            "truncation must be to max_length {max_tokens}, the file has {other:?}"))),
    }
    // The tokenizers crate subtracts the special tokens from max_length (usize): make sure
    // that cannot underflow for any prompt.
    if max_tokens < tok.get_post_processor().map_or(0, |p| p.added_tokens(false)) + 1 {
        return Err(Error::bundle(path, format!("max_tokens {max_tokens} leaves no room for text")));
    }
    Ok(tok)
}

#[allow(dead_code)]
fn _assert_send_sync() {
    fn is_send_sync<T: Send + Sync>() {}
    is_send_sync::<TextEncoder>();
}
