//! `manifest.json` as Rust types, mirroring the schema in the Python exporter's docstring
//! (`training/src/comgrasp_train/export/bundle.py`), version 1.
//!
//! Every section the engine interprets uses `deny_unknown_fields`: the manifest is the
//! contract between the two halves of the repository, and a field this reader does not
//! know may change what the other fields mean (a quantized cache, another pooling, ...),
//! so an exporter change must come with the matching change here rather than be silently
//! ignored. Free-form sections (`provenance`, the text encoder's informational
//! `tokenizer` settings and `parity` summary) are kept as raw JSON values.
//!
//! Parsing alone guarantees types (non-negative sizes, arrays of the right arity);
//! consistency between fields and with the files is checked by `bundle::verify`.
use std::collections::BTreeMap;
use std::ops::Range;

use serde::{Deserialize, Serialize};

/// The `format` value of a bundle manifest.
pub const FORMAT: &str = "comgrasp-bundle";
/// The only manifest version this reader understands.
pub const VERSION: u64 = 1;
/// Name of the manifest inside the bundle directory.
pub const MANIFEST_FILE: &str = "manifest.json";
/// Width of the per-frame feature vector (DESIGN §2).
pub const FRAME_DIM: usize = 335;
/// Number of components / Transformer streams.
pub const N_STREAMS: usize = 4;
/// Component (stream) names, in the order used everywhere.
pub const STREAMS: [&str; N_STREAMS] = ["global", "body", "lhand", "rhand"];
/// Feature channels that hold a contact probability (left, right).
pub const CONTACT_CHANNELS: [usize; 2] = [240, 334];
/// Joints of the SMPL-X tree.
pub const NUM_JOINTS: usize = 55;

/// The whole manifest.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub format: String,
    pub version: u64,
    /// Frames per second of the decoded motion.
    pub fps: f64,
    /// Frames one token decodes to (16).
    pub frames_per_token: usize,
    /// Longest sequence in tokens (block_size - 2).
    pub l_max: usize,
    /// 335.
    pub frame_dim: usize,
    pub layout: Vec<LayoutField>,
    pub components: Vec<Component>,
    pub normalization: Normalization,
    pub text_encoder: TextEncoderSpec,
    pub transformer: TransformerSpec,
    pub decoder: DecoderSpec,
    pub skeleton: Skeleton,
    pub objects: Vec<ObjectEntry>,
    pub sampling: SamplingDefaults,
    pub parity: ParitySection,
    /// `{relative path: {sha256, bytes}}` of every file but manifest.json.
    pub files: BTreeMap<String, FileEntry>,
    /// Free-form: exporter versions, configs, commands, data, git, metrics.
    pub provenance: serde_json::Value,
}

/// One named field of the 335-D frame.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayoutField {
    pub name: String,
    pub start: usize,
    pub stop: usize,
    pub component: String,
}

/// One component: its slice of the frame and the ids of its Transformer vocabulary.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Component {
    pub name: String,
    pub index: usize,
    /// `[start, stop)` in the 335-D frame.
    pub slice: [usize; 2],
    /// J: codes are 0..J.
    pub codebook_size: usize,
    /// = J.
    pub end_id: usize,
    /// = J + 1.
    pub pad_id: usize,
    /// = J + 2.
    pub vocab_size: usize,
}

impl Component {
    /// The component's channels of the frame.
    pub fn range(&self) -> Range<usize> {
        self.slice[0]..self.slice[1]
    }
}

/// `features = normalized * std + mean`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Normalization {
    pub mean: Vec<f32>,
    pub std: Vec<f32>,
    pub dtype: String,
    pub rule: String,
}

/// Element type of a graph input or output.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Dtype {
    #[serde(rename = "int64")]
    Int64,
    #[serde(rename = "float32")]
    Float32,
}

impl std::fmt::Display for Dtype {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Dtype::Int64 => "int64",
            Dtype::Float32 => "float32",
        })
    }
}

/// One graph input or output as the manifest declares it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IoSpec {
    pub name: String,
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    /// Human-readable description (text encoder inputs only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub value: Option<String>,
}

/// How token states become one sentence embedding.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Pooling {
    /// Masked mean over the tokens (MiniLM).
    Mean,
    /// The state at the EOS position (CLIP).
    Eos,
}

/// Which token is "the EOS position" for [`Pooling::Eos`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EosSelection {
    /// The first token whose id is `eos_id`.
    FirstEos,
    /// The first token holding the largest id.
    ArgmaxId,
}

/// The text encoder's files.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TextEncoderFiles {
    pub onnx: String,
    pub tokenizer: String,
}

/// The text encoder fragment (export/text_encoder_export.py `manifest_fragment`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TextEncoderSpec {
    /// "minilm" or "clip".
    pub kind: String,
    pub name: String,
    pub files: TextEncoderFiles,
    pub opset: u32,
    /// T: the tokenizer pads and truncates to exactly this many tokens.
    pub max_tokens: usize,
    /// Width of `last_hidden_state`.
    pub hidden: usize,
    /// Width of the pooled embedding (= the Transformer's d_text).
    pub dim: usize,
    pub inputs: Vec<IoSpec>,
    pub outputs: Vec<IoSpec>,
    /// Name of the output that is pooled.
    pub pool_output: String,
    pub pooling: Pooling,
    pub mean_eps: f64,
    pub eos_id: Option<i64>,
    pub eos_selection: Option<EosSelection>,
    pub normalize: bool,
    pub norm_eps: f64,
    pub pad_id: i64,
    /// Informational copy of the tokenizer settings (they are inside tokenizer.json).
    pub tokenizer: serde_json::Value,
    #[serde(default)]
    pub sha256: BTreeMap<String, String>,
    #[serde(default)]
    pub size_bytes: BTreeMap<String, u64>,
    /// Informational summary of the text parity cases.
    #[serde(default)]
    pub parity: Option<serde_json::Value>,
    /// Weights for the native text encoder (BERT layout only), when the exporter wrote them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub native: Option<TextNativeSpec>,
}

/// `text_encoder.native`: a BERT encoder's tensors (`dir`, `tensors` as in [`NativeSpec`],
/// named as `BertTokenStates.state_dict()`) and what the shapes do not say.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TextNativeSpec {
    pub dir: String,
    /// Attention heads per layer (the head width is hidden / heads).
    pub heads: usize,
    pub layer_norm_eps: f64,
    /// The feed-forward activation; only "gelu" (exact, erf) is supported.
    pub activation: String,
    pub tensors: BTreeMap<String, NativeTensor>,
}

impl TextNativeSpec {
    /// The tensors as a plain [`NativeSpec`] (what the weight reader takes).
    pub fn weights(&self) -> NativeSpec {
        NativeSpec { dir: self.dir.clone(), tensors: self.tensors.clone() }
    }
}

/// The 4-stream step graph (export/step_graph.py).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransformerSpec {
    pub file: String,
    pub opset: u32,
    pub batch: usize,
    pub n_layers: usize,
    pub n_heads: usize,
    pub widths: Vec<usize>,
    pub head_dims: Vec<usize>,
    pub d_text: usize,
    pub block_size: usize,
    /// = block_size = l_max + 2.
    pub cache_slots: usize,
    pub inputs: Vec<IoSpec>,
    pub outputs: Vec<IoSpec>,
    pub cache_init: String,
    pub cache_update: String,
    pub steps: String,
    /// Weights for the native step (src/model/native), when the exporter wrote them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub native: Option<NativeSpec>,
}

/// dtype of a native-path tensor file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NativeDtype {
    Float32,
    /// int8 per row, with `<name>.scale.npy` (float32, one per row).
    Int8,
    /// int4 per row (embedding tables only): `<name>.npy` is uint8 `(rows, ceil(cols / 2))`,
    /// column `2j` in byte `j`'s low nibble and `2j + 1` in its high one, each `q + 8`; the
    /// manifest's shape is the logical `(rows, cols)`; `<name>.scale.npy` as for int8.
    Int4,
}

/// One tensor of a native section.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NativeTensor {
    pub dtype: NativeDtype,
    pub shape: Vec<usize>,
}

/// A `native` section: the PyTorch tensors of a graph, one `.npy` each under `dir`
/// (export/native_weights.py), keyed by `state_dict` name.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NativeSpec {
    pub dir: String,
    pub tensors: BTreeMap<String, NativeTensor>,
}

/// The streaming decoder step graph (export/decoder_graph.py).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DecoderSpec {
    pub file: String,
    pub opset: u32,
    pub batch: usize,
    pub frames_per_token: usize,
    /// K: tokens one chunk depends on, the newest included.
    pub context_tokens: usize,
    /// K - 1.
    pub state_tokens: usize,
    /// = the codebook sizes.
    pub state_pad_ids: Vec<i64>,
    /// (1, 4, K-1) state of a new sequence.
    pub initial_state: Vec<Vec<Vec<i64>>>,
    pub inputs: Vec<IoSpec>,
    pub outputs: Vec<IoSpec>,
    pub output_is_normalized: bool,
    pub contact_channels: Vec<usize>,
    pub contact_is_probability: bool,
    pub contact_threshold: f64,
    /// Weights for the native decoder (src/model/native), when the exporter wrote them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub native: Option<NativeSpec>,
}

/// The body skeleton used for forward kinematics.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Skeleton {
    pub joint_names: Vec<String>,
    /// Parent of each joint, -1 for the root; parents come before children.
    pub parents: Vec<i32>,
    /// Rest joint positions, metres.
    pub rest_joints: Vec<[f32; 3]>,
    pub units: String,
    pub frame: String,
}

/// Longest catalogue object name, bytes (a C host gets it in a fixed buffer).
pub const OBJECT_NAME_MAX: usize = 63;

/// One catalogue object.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectEntry {
    pub name: String,
    pub aliases: Vec<String>,
    /// Mesh path relative to the bundle root.
    pub mesh: String,
    /// Bounding-box centre in the object frame.
    pub centre: [f32; 3],
    pub half_extents: [f32; 3],
}

/// Default sampling parameters (models/sampling.py's rule).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SamplingDefaults {
    /// 0 = greedy.
    pub temperature: f64,
    /// 0 = off.
    pub top_k: usize,
    pub min_len: usize,
    pub max_len: usize,
    pub seed: u64,
    /// "splitmix64".
    pub rng: String,
    pub stop: String,
    /// Classifier-free guidance scale (DESIGN §4); 1 = the prompt alone, also for bundles
    /// exported before guidance existed.
    #[serde(default = "unguided")]
    pub guidance: f64,
}

fn unguided() -> f64 {
    1.0
}

/// Where the parity vectors are and how well onnxruntime matched PyTorch at export.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParitySection {
    /// Path of parity/index.json.
    pub index: String,
    pub tolerances: BTreeMap<String, f64>,
    pub max_abs_diff: BTreeMap<String, f64>,
    pub tokens_match: bool,
}

/// Size and digest of one bundle file.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileEntry {
    /// Lower-case hex SHA-256.
    pub sha256: String,
    pub bytes: u64,
}

impl Manifest {
    /// Codebook sizes J of the four components.
    pub fn codebook_sizes(&self) -> [usize; N_STREAMS] {
        std::array::from_fn(|i| self.components[i].codebook_size)
    }

    /// Vocabulary sizes (J + 2) of the four streams.
    pub fn vocab_sizes(&self) -> [usize; N_STREAMS] {
        std::array::from_fn(|i| self.components[i].vocab_size)
    }

    /// End ids (J) of the four streams.
    pub fn end_ids(&self) -> [usize; N_STREAMS] {
        std::array::from_fn(|i| self.components[i].end_id)
    }

    /// Pad ids (J + 1), the tokens to feed at the condition step (pos 0).
    pub fn pad_ids(&self) -> [i64; N_STREAMS] {
        // pad_id < vocab_size was verified at load; usize -> i64 cannot overflow for a
        // vocabulary that fits in memory.
        std::array::from_fn(|i| self.components[i].pad_id as i64)
    }

    /// The catalogue object named `name` or having it as an alias (ASCII case-insensitive).
    pub fn find_object(&self, name: &str) -> Option<&ObjectEntry> {
        let name = name.trim();
        self.objects
            .iter()
            .find(|o| o.name.eq_ignore_ascii_case(name))
            .or_else(|| self.objects.iter().find(|o| o.aliases.iter().any(|a| a.eq_ignore_ascii_case(name))))
    }
}

/// The catalogue object the prompt names: the longest name or alias that occurs in the
/// lower-cased prompt starting at a word boundary ("a coffee mug" prefers "coffee mug"
/// over "mug"; "cubes" still finds "cube", "smuggle" does not find "mug"). Without any
/// match, the first object and `None`. `None` overall only for an empty catalogue.
pub fn choose_object(objects: &[ObjectEntry], prompt: &str) -> Option<(usize, Option<String>)> {
    let prompt = prompt.to_lowercase();
    let mut best: Option<(usize, &str)> = None;
    for (i, o) in objects.iter().enumerate() {
        for name in std::iter::once(&o.name).chain(&o.aliases) {
            let name = name.trim();
            if name.is_empty() || !occurs_at_word_start(&prompt, &name.to_lowercase()) {
                continue;
            }
            if best.is_none_or(|(_, b)| name.len() > b.len()) {
                best = Some((i, name));
            }
        }
    }
    match best {
        Some((i, name)) => Some((i, Some(name.to_string()))),
        None => (!objects.is_empty()).then_some((0, None)),
    }
}

fn occurs_at_word_start(haystack: &str, needle: &str) -> bool {
    haystack.match_indices(needle).any(|(at, _)| !haystack[..at].chars().next_back().is_some_and(char::is_alphanumeric))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(name: &str, aliases: &[&str]) -> ObjectEntry {
        ObjectEntry {
            name: name.into(),
            aliases: aliases.iter().map(|a| a.to_string()).collect(),
            mesh: format!("objects/{name}.obj"),
            centre: [0.0; 3],
            half_extents: [0.1; 3],
        }
    }

    #[test]
    fn the_longest_alias_at_a_word_start_wins() {
        let cat = [
            entry("mug", &["mug", "coffee mug", "cup of coffee"]),
            entry("cubesmall", &["small cube", "cube", "block"]),
            entry("waterbottle", &["water bottle", "bottle"]),
        ];
        let pick = |p: &str| choose_object(&cat, p).map(|(i, a)| (cat[i].name.as_str().to_owned(), a));
        assert_eq!(pick("A woman drinks from the mug"), Some(("mug".into(), Some("mug".into()))));
        assert_eq!(pick("Lift the SMALL CUBE."), Some(("cubesmall".into(), Some("small cube".into()))));
        assert_eq!(
            pick("pour from the water bottle into a mug"),
            Some(("waterbottle".into(), Some("water bottle".into())))
        );
        assert_eq!(pick("stack the cubes"), Some(("cubesmall".into(), Some("cube".into()))));
        assert_eq!(pick("he smuggles nothing"), Some(("mug".into(), None)));
        assert_eq!(pick("wave"), Some(("mug".into(), None)));
        assert_eq!(choose_object(&[], "mug"), None);
    }
}
