//! Text -> one sentence embedding: the bundle's `tokenizer.json` (Hugging Face `tokenizers`
//! 0.22), then the encoder's token states, pooled and L2-normalized here.
//!
//! The token states come from the native BERT encoder (`model::native::text`) when the
//! bundle has `text_encoder.native` weights (the default bundle does), else from
//! `text_encoder.onnx` in tract (`text_graph`, cargo feature `onnx`); [`TextBackend`]
//! picks one explicitly. Both run only the prompt's real tokens where they can
//! ([`SequenceMode`]).
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

use tokenizers::Tokenizer;

use super::native::text::NativeText;
#[cfg(feature = "onnx")]
use super::text_graph::GraphText;
use crate::bundle::manifest::{EosSelection, Manifest, Pooling};
use crate::bundle::BundleSource;
use crate::error::{Error, Result};

/// Longest prompt accepted, in UTF-8 bytes.
pub const MAX_TEXT_BYTES: usize = 4096;

/// Which implementation computes the token states.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TextBackend {
    /// Native when the bundle has `text_encoder.native`, tract otherwise.
    #[default]
    Auto,
    /// The Rust kernels; an error at load if the bundle has no native text weights.
    Native,
    /// `text_encoder.onnx` in tract (needs the cargo feature `onnx`).
    Tract,
}

/// Which tokens a call runs (`text_graph`'s module doc, "Speed").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SequenceMode {
    /// The sequence axis was made symbolic at load: a call runs only the tokens the pooling
    /// reads (the real ones).
    RealTokens,
    /// The graph as exported: every call runs all `max_tokens` positions.
    Padded,
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

/// Tokenizer + encoder + pooling rule; shared by all streams (`Send + Sync`).
pub struct TextEncoder {
    tokenizer: Tokenizer,
    backend: Backend,
    width: usize,
    max_tokens: usize,
    pooling: Pooling,
    eos_id: Option<i64>,
    eos_selection: Option<EosSelection>,
    normalize: bool,
    mean_eps: f64,
    norm_eps: f64,
}

enum Backend {
    Native(Box<NativeText>),
    #[cfg(feature = "onnx")]
    Graph(GraphText),
}

impl std::fmt::Debug for TextEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TextEncoder")
            .field("backend", &self.backend())
            .field("max_tokens", &self.max_tokens)
            .field("dim", &self.width)
            .field("pooling", &self.pooling)
            .field("normalize", &self.normalize)
            .field("mode", &self.sequence_mode())
            .field("fallback", &self.fallback_reason())
            .finish_non_exhaustive()
    }
}

impl TextEncoder {
    /// Loads the tokenizer and the encoder named by the (verified) manifest (native when
    /// the bundle has its weights) and checks that the tokenizer pads and truncates to
    /// exactly `max_tokens`.
    pub fn load(src: &BundleSource, m: &Manifest) -> Result<TextEncoder> {
        Self::load_with(src, m, TextBackend::Auto)
    }

    /// [`load`](Self::load) with the given backend.
    pub fn load_with(src: &BundleSource, m: &Manifest, backend: TextBackend) -> Result<TextEncoder> {
        let t = &m.text_encoder;
        let tok_path = src.path_of(&t.files.tokenizer);
        let tokenizer = load_tokenizer(&tok_path, &src.read_file(&t.files.tokenizer)?, t.max_tokens)?;
        // The probe is checked (and its error reported) after the encoder, as before; the
        // graph loader only uses it to validate the real-tokens form.
        let probe = tokenize_with(&tokenizer, t.max_tokens, "a test prompt");
        let backend = match (backend, &t.native) {
            (TextBackend::Auto | TextBackend::Native, Some(spec)) => {
                Backend::Native(Box::new(NativeText::load(src, t, spec)?))
            }
            (TextBackend::Native, None) => {
                return Err(Error::bundle(
                    src.path_of(crate::bundle::manifest::MANIFEST_FILE),
                    "the text backend is native, but the bundle has no text_encoder.native weights",
                ));
            }
            #[cfg(feature = "onnx")]
            (TextBackend::Auto | TextBackend::Tract, _) => {
                if src.omits(&t.files.onnx) {
                    return Err(Error::bundle(
                        src.path_of(&t.files.onnx),
                        "the embedded default bundle holds only the native text encoder, not its ONNX graph; \
                         for the tract backend load the bundle directory (models/default of the source tree)",
                    ));
                }
                Backend::Graph(GraphText::load(src, t, probe.as_ref().ok())?)
            }
            #[cfg(not(feature = "onnx"))]
            (TextBackend::Auto | TextBackend::Tract, _) => return Err(super::step::no_onnx(src, &t.files.onnx)),
        };
        let enc = TextEncoder {
            tokenizer,
            backend,
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
        let probe = probe.map_err(|e| Error::bundle(&tok_path, e.to_string()))?;
        if probe.input_ids.len() != t.max_tokens {
            return Err(Error::bundle(
                &tok_path,
                format!("pads to {} tokens, manifest max_tokens is {}", probe.input_ids.len(), t.max_tokens),
            ));
        }
        Ok(enc)
    }

    /// The implementation that computes the token states: `Native` or `Tract` (never `Auto`).
    pub fn backend(&self) -> TextBackend {
        match self.backend {
            Backend::Native(_) => TextBackend::Native,
            #[cfg(feature = "onnx")]
            Backend::Graph(_) => TextBackend::Tract,
        }
    }

    /// Width of the embedding.
    pub fn dim(&self) -> usize {
        self.width
    }

    /// Tokens per prompt (fixed).
    pub fn max_tokens(&self) -> usize {
        self.max_tokens
    }

    /// Which tokens a call runs (the native encoder: the real ones).
    pub fn sequence_mode(&self) -> SequenceMode {
        match &self.backend {
            Backend::Native(_) => SequenceMode::RealTokens,
            #[cfg(feature = "onnx")]
            Backend::Graph(g) => g.mode,
        }
    }

    /// Why the graph runs padded or unrewritten, when a faster form was refused.
    pub fn fallback_reason(&self) -> Option<&str> {
        match &self.backend {
            Backend::Native(_) => None,
            #[cfg(feature = "onnx")]
            Backend::Graph(g) => g.fallback.as_deref(),
        }
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
    /// before pooling (for parity tests and diagnostics). In [`SequenceMode::RealTokens`]
    /// the rows of padding tokens are not computed and are zeros.
    pub fn token_states(&self, text: &str) -> Result<(TokenizedText, Vec<f32>)> {
        let tok = self.tokenize(text)?;
        let len = self.rows_needed(&tok)?;
        let mut states = match &self.backend {
            Backend::Native(n) => n.token_states(&tok.input_ids[..len], &tok.token_type_ids[..len])?,
            #[cfg(feature = "onnx")]
            Backend::Graph(g) => g.run(&tok, len)?,
        };
        states.resize(self.max_tokens * self.width, 0.0);
        Ok((tok, states))
    }

    /// How many leading tokens the graph must run for the pooling to see every row it
    /// reads: all of them when padded; else up to the last real token (and the EOS row).
    fn rows_needed(&self, tok: &TokenizedText) -> Result<usize> {
        if self.sequence_mode() == SequenceMode::Padded {
            return Ok(self.max_tokens);
        }
        let mut len = tok.attention_mask.iter().rposition(|&m| m != 0).map_or(1, |i| i + 1);
        if self.pooling == Pooling::Eos {
            len = len.max(self.eos_position(&tok.input_ids)? + 1);
        }
        Ok(len.min(self.max_tokens))
    }

    /// The row `eos` pooling reads.
    fn eos_position(&self, ids: &[i64]) -> Result<usize> {
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
        at.ok_or_else(|| Error::Inference("the tokenized text has no EOS token".into()))
    }

    /// Tokenizes `text` exactly as the encoder will see it.
    pub fn tokenize(&self, text: &str) -> Result<TokenizedText> {
        tokenize_with(&self.tokenizer, self.max_tokens, text)
    }

    /// Pools (T, width) token states into one embedding (module doc).
    pub(crate) fn pool(&self, states: &[f32], tok: &TokenizedText) -> Result<Vec<f32>> {
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
                let at = self.eos_position(&tok.input_ids)?;
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

/// [`TextEncoder::tokenize`] with an explicit tokenizer (used before the encoder exists).
pub(crate) fn tokenize_with(tokenizer: &Tokenizer, max_tokens: usize, text: &str) -> Result<TokenizedText> {
    if text.trim().is_empty() {
        return Err(Error::InvalidArgument("text is empty".into()));
    }
    if text.len() > MAX_TEXT_BYTES {
        return Err(Error::InvalidArgument(format!(
            "text is {} bytes long, the limit is {MAX_TEXT_BYTES}",
            text.len()
        )));
    }
    let enc = match catch_unwind(AssertUnwindSafe(|| tokenizer.encode_fast(text, true))) {
        Ok(Ok(enc)) => enc,
        Ok(Err(e)) => return Err(Error::Inference(format!("tokenizer: {e}"))),
        Err(_) => return Err(Error::Inference("tokenizer panicked".into())),
    };
    let ids = enc.get_ids();
    if ids.len() != max_tokens {
        return Err(Error::Inference(format!(
            "tokenizer produced {} tokens, the encoder takes exactly {max_tokens}",
            ids.len()
        )));
    }
    let widen = |v: &[u32]| v.iter().map(|&x| i64::from(x)).collect::<Vec<i64>>();
    Ok(TokenizedText {
        input_ids: widen(ids),
        attention_mask: widen(enc.get_attention_mask()),
        token_type_ids: widen(enc.get_type_ids()),
        truncated: !enc.get_overflowing().is_empty(),
    })
}

/// Parses tokenizer.json (`bytes`; `path` names it in errors) and checks its
/// padding/truncation settings against `max_tokens`.
pub(crate) fn load_tokenizer(path: &Path, bytes: &[u8], max_tokens: usize) -> Result<Tokenizer> {
    let tok = match catch_unwind(|| Tokenizer::from_bytes(bytes)) {
        Ok(Ok(t)) => t,
        Ok(Err(e)) => return Err(Error::bundle(path, format!("not a valid tokenizers JSON: {e}"))),
        Err(_) => return Err(Error::bundle(path, "the tokenizers crate panicked while reading it")),
    };
    use tokenizers::{PaddingDirection, PaddingStrategy, PostProcessor};
    match tok.get_padding() {
        Some(p)
            if matches!(p.strategy, PaddingStrategy::Fixed(n) if n == max_tokens)
                && matches!(p.direction, PaddingDirection::Right) => {}
        other => {
            return Err(Error::bundle(
                path,
                format!("padding must be Fixed({max_tokens}) to the right, the file has {other:?}"),
            ))
        }
    }
    match tok.get_truncation() {
        Some(t) if t.max_length == max_tokens => {}
        other => {
            return Err(Error::bundle(
                path,
                format!("truncation must be to max_length {max_tokens}, the file has {other:?}"),
            ))
        }
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

#[cfg(test)]
pub(crate) mod test_support {
    use std::path::Path;

    use crate::bundle::manifest::Manifest;
    use crate::bundle::{verify, BundleSource};

    pub(crate) const PROMPTS: [&str; 5] = [
        "pick up the mug",
        "Café: grasp the APPLE & inspect it (carefully)!",
        "a",
        "lift the wine glass with the right hand, then toast",
        // longer than max_tokens: truncated, every position real
        "the person walks to the table, picks up the small blue cup with the left hand, turns it \
         around slowly to look at the bottom, passes it to the right hand and puts it back",
    ];

    /// The committed bundles with a text encoder (models/default may be absent in a
    /// checkout without the large files).
    pub(crate) fn bundles() -> Vec<(BundleSource, Manifest)> {
        ["models/tiny", "models/default"]
            .iter()
            .map(|d| Path::new(env!("CARGO_MANIFEST_DIR")).join(d))
            .filter(|d| d.join("text_encoder.onnx").is_file())
            .map(|d| {
                let src = BundleSource::dir(&d);
                let m = verify::read_manifest(&src).unwrap();
                (src, m)
            })
            .collect()
    }

    pub(crate) fn max_abs(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()))
    }
}

#[cfg(all(test, feature = "onnx"))]
mod tests {
    use super::test_support::{bundles, max_abs, PROMPTS};
    use super::*;

    /// The native encoder computes the graph's function: the same token states to float
    /// rounding (the products sum in another order) and the same embeddings.
    #[test]
    fn native_encoder_matches_the_graph() {
        let mut checked = 0;
        for (src, m) in bundles().into_iter().filter(|(_, m)| m.text_encoder.native.is_some()) {
            let native = TextEncoder::load(&src, &m).unwrap();
            assert_eq!(native.backend(), TextBackend::Native);
            let graph = TextEncoder::load_with(&src, &m, TextBackend::Tract).unwrap();
            assert_eq!(graph.backend(), TextBackend::Tract);
            let w = native.dim();
            for prompt in PROMPTS {
                let (tok, a) = native.token_states(prompt).unwrap();
                let (_, b) = graph.token_states(prompt).unwrap();
                let n = tok.attention_mask.iter().filter(|&&x| x != 0).count();
                let scale = b.iter().fold(1f32, |m, v| m.max(v.abs()));
                let d = max_abs(&a, &b);
                assert!(d <= 1e-4 * scale, "{prompt:?}: states differ by {d:e} (scale {scale})");
                assert!(a[n * w..].iter().all(|&v| v == 0.0), "padding rows are not computed");
                let d = max_abs(&native.embed(prompt).unwrap(), &graph.embed(prompt).unwrap());
                assert!(d <= 1e-5, "{prompt:?}: embeddings differ by {d:e}");
                checked += 1;
            }
        }
        // models/default carries native text weights; a checkout without it checks nothing.
        if Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default/manifest.json").is_file() {
            assert!(checked > 0, "models/default has no text_encoder.native");
        }
    }

    #[test]
    fn native_backend_needs_native_weights() {
        let (src, m) = bundles().into_iter().find(|(_, m)| m.text_encoder.native.is_none()).unwrap();
        let e = TextEncoder::load_with(&src, &m, TextBackend::Native).unwrap_err().to_string();
        assert!(e.contains("no text_encoder.native"), "{e}");
        assert_eq!(TextEncoder::load(&src, &m).unwrap().backend(), TextBackend::Tract);
    }

    #[test]
    fn a_bad_native_layout_is_refused() {
        let Some((src, m)) = bundles().into_iter().find(|(_, m)| m.text_encoder.native.is_some()) else { return };
        let cases: [(&str, fn(&mut Manifest)); 3] = [
            ("activation", |m| m.text_encoder.native.as_mut().unwrap().activation = "relu".into()),
            ("heads do not divide", |m| m.text_encoder.native.as_mut().unwrap().heads = 5),
            ("tensors", |m| {
                let n = m.text_encoder.native.as_mut().unwrap();
                let extra = n.tensors.values().next().unwrap().clone();
                n.tensors.insert("layers.0.extra".into(), extra);
            }),
        ];
        for (want, mutate) in cases {
            let mut bad = m.clone();
            mutate(&mut bad);
            let e = TextEncoder::load(&src, &bad).unwrap_err().to_string();
            assert!(e.contains(want), "{want}: {e}");
        }
    }
}
