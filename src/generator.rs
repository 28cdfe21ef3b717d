//! One generation: text → condition → token steps → decoded 16-frame chunks → assembled
//! frames, as a [`ChunkSource`] driven by a stream's worker thread (one decode per
//! `next_chunk` call, so a cancel is seen within one call: one token step, or G of them
//! when decodes are grouped, plus the decode).
//!
//! Per call, at step `k` (DESIGN §3, `sampler` docs):
//! 1. first call only: `TextEncoder::embed(text)`; step 0's input is the condition token
//!    (the graph projects the embedding) with the Pad ids as tokens;
//! 2. `StepModel::step(tokens of step k-1, pos = k)` → logits → `TokenSampler::sample_step`
//!    (unless the previous call already ran step k, see *overlap*);
//! 3. if any stream sampled its End id, the sequence has `k` codes: stop;
//! 4. *decode group*: after the first call, steps k+1 .. k+G-1 run too (stopping at End or
//!    the step limit; with overlap they already ran during the previous call's decode),
//!    G = [`decode_group::tokens_per_decode`] (4 on the default bundle);
//! 5. decode those codes in one call (G chunks of F = 16 normalized frames, the same bits
//!    as one decode per token) → `FrameAssembler::assemble`.
//!
//! The first call decodes its token alone, so the time to first frame does not wait for
//! a group.
//!
//! **Overlap.** When [`overlap::overlaps`](crate::model::overlap::overlaps) says so (both
//! models native, the step no bigger than the decoder: the default bundle), the steps of
//! the *next* group (one after the first chunk, then G) run, each sampled, on one thread
//! while the decoder's jobs decode this group on both
//! ([`overlap::decode_and_steps`](crate::model::overlap::decode_and_steps)); the next call
//! decodes those codes. Same tokens and frames (docs/performance.md for the speed).
//!
//! **`is_last`.** Whether a call's last chunk is the sequence's last is decided at the
//! *next* step (End sampled there). With overlap that step has run by the time the chunks
//! are assembled, so every frame goes out at once with the right `is_last`. Without it,
//! all but the final frame go out as soon as they are decoded and the final frame is held
//! until the next step has decided, then emitted with the right `is_last` (1 if that step
//! sampled End). Either way:
//! * `is_last` is exact and set on a real frame (no marker frame, no frame patched after
//!   it was handed out);
//! * when held, the final frame arrives one call late, while the host is still playing
//!   the chunk's first F-1 frames (~0.5 s at 30 fps versus a call of a few ms), so
//!   playback never waits for it;
//! * when End is sampled inside a group or the step limit forces it, nothing is held: the
//!   final chunk goes out whole, its last frame marked, without running the forced step;
//! * if End is sampled at step 0 (possible only with `min_len = 0`) the stream has no
//!   frames and ends directly (poll reports End without any frame).
use std::collections::VecDeque;
use std::sync::Arc;

use parking_lot::Mutex;

use crate::anchor::AnchorStage;
use crate::assemble::{FrameAssembler, Pose};
use crate::bundle::choose_object;
use crate::bundle::N_STREAMS;
use crate::config::{guidance_scale, EngineConfig, StreamConfig};
use crate::contact::{heading, smoothstep, ContactStage, GraspOnset, ObjectShape, ObjectSurface, PLACE_LOOKAHEAD};
use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::model::{decode_group, overlap, Bundle, DecodeJob, DecoderState, StepJob, StepState, MAX_DECODE_GROUP};
use crate::sampler::{SamplingParams, TokenSampler};
use crate::skeleton::{mat_vec, transpose, Mat3, Vec3};

/// Where a stream's frames come from. The real implementation is
/// [`Generator`] (text → tokens → decoded, assembled frames); tests use
/// deterministic doubles.
pub trait ChunkSource: Send {
    /// Produces the next chunk (normally 16 frames per decoded token, already assembled, with `stream_id`,
    /// consecutive `frame_index` and a correct `is_last`) by appending to `out`, which the
    /// caller passes in empty. Returns `Ok(true)` when more chunks follow and `Ok(false)` when
    /// this chunk (possibly empty) was the last one. Must return promptly (a few token
    /// steps at most): cancellation is checked between calls.
    fn next_chunk(&mut self, out: &mut Vec<Frame>) -> Result<bool>;

    /// The most frames one `next_chunk` call appends: the worker reserves this much once, so
    /// its loop never reallocates. A source may exceed it (the vector grows).
    fn max_chunk_frames(&self) -> usize {
        16
    }

    /// The catalogue object the frames' object is, when the source knows one.
    fn object(&self) -> Option<StreamObject> {
        None
    }
}

/// Which catalogue object a stream's object is: the one its prompt names, or the
/// catalogue's first when it names none (`bundle::choose_object`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StreamObject {
    /// Index in the bundle's catalogue (manifest `objects`).
    pub index: usize,
    /// The catalogue name.
    pub name: String,
    /// The name or alias found in the prompt; `None`: the prompt names no catalogue object.
    pub alias: Option<String>,
}

/// What a [`SourceFactory`] gets for one new stream.
#[derive(Debug)]
pub struct StreamRequest<'a> {
    /// The new stream's id; every frame must carry it.
    pub stream_id: u64,
    /// The prompt, already validated (non-blank, at most [`MAX_TEXT_BYTES`](crate::config::MAX_TEXT_BYTES)).
    pub text: &'a str,
    /// The stream's settings merged with the engine defaults (bundle defaults not applied).
    pub config: &'a StreamConfig,
}

/// Builds the [`ChunkSource`] of a new stream. Runs on the thread that calls
/// `Engine::start`, so it should only set up state (cheap); heavy work (text encoding,
/// token steps) belongs in `next_chunk`, on the worker.
pub type SourceFactory = Box<dyn Fn(&StreamRequest<'_>) -> Result<Box<dyn ChunkSource>> + Send + Sync>;

/// Loads the bundle the config selects (`bundle::select`: the path, else `COMGRASP_BUNDLE`,
/// else the embedded default), verifying it, and returns it with the factory that builds
/// one [`Generator`] per stream. Everything expensive (graph loading, the assembler)
/// happens here, once per engine.
pub fn source_factory(config: &EngineConfig) -> Result<(Arc<Pipeline>, SourceFactory)> {
    let bundle = Bundle::select(config.bundle_path.as_deref(), &config.runtime)?;
    let pipeline = Arc::new(Pipeline::new(bundle, config)?);
    let pipe = Arc::clone(&pipeline);
    let factory: SourceFactory = Box::new(move |req: &StreamRequest<'_>| -> Result<Box<dyn ChunkSource>> {
        Ok(Box::new(Generator::new(Arc::clone(&pipe), req)?))
    });
    Ok((pipeline, factory))
}

/// What every stream of an engine shares: the bundle and the frame assembler.
pub struct Pipeline {
    bundle: Arc<Bundle>,
    assembler: FrameAssembler,
    end_ids: [usize; N_STREAMS],
    pad_ids: [i64; N_STREAMS],
    /// Step k+1 runs with the decode of chunk k (`model::overlap`).
    overlap: bool,
    /// Tokens per decode after the first chunk (`model::decode_group`).
    group: usize,
    /// Where the most recent ended streams left off, newest last (`continue_from`).
    ended: Mutex<VecDeque<(u64, Arc<Continuation>)>>,
    /// Each catalogue object's surface (from its mesh), for the contact stage's grasps.
    surfaces: Vec<Arc<ObjectSurface>>,
    /// The most recently used prompts' text embeddings, newest last: a crowd starting many
    /// streams with the same prompt encodes it once (the encoder is ~4.5 ms of the default
    /// bundle's ~10 ms to a first frame).
    embeddings: Mutex<VecDeque<(String, Arc<[f32]>)>>,
}

/// Prompts whose embeddings a pipeline keeps.
pub const KEEP_EMBEDDINGS: usize = 64;

/// Ended streams a new one can continue from (the oldest is forgotten first).
pub const KEEP_ENDED: usize = 64;
/// Frames over which a continued stream blends its body from the earlier stream's last pose.
pub const BLEND_FRAMES: u64 = 15;

/// Where a stream left off: what a stream that continues it starts from.
#[derive(Clone, Debug)]
pub struct Continuation {
    /// The last frame in the host's world (native), after every stage.
    pose: Pose,
    /// The contact stage's state in the host's world (None: raw output).
    contact: Option<ContactStage>,
    /// The character's ground point there.
    ground: Vec3,
    object: StreamObject,
}

impl Pipeline {
    /// Builds the assembler for the engine's coordinate system and FK setting.
    pub fn new(bundle: Arc<Bundle>, config: &EngineConfig) -> Result<Pipeline> {
        let m = &bundle.manifest;
        let manifest_path = bundle.origin().path_of(crate::bundle::manifest::MANIFEST_FILE);
        let assembler = FrameAssembler::new(
            &m.normalization.mean,
            &m.normalization.std,
            &m.skeleton.parents,
            &m.skeleton.rest_joints,
            config.coordinate_system,
            config.enable_fk,
            m.fps,
        )
        // Bad normalization or skeleton data is a bundle defect, not a caller error.
        .map_err(|e| Error::bundle(&manifest_path, e.to_string()))?;
        let pad_ids = m.pad_ids();
        if pad_ids.iter().any(|&p| p < 0) {
            return Err(Error::bundle(&manifest_path, "negative pad id"));
        }
        let overlap = overlap::overlaps(&bundle.step, &bundle.decoder, config.runtime.overlap);
        let group = decode_group::tokens_per_decode(&bundle.step, &bundle.decoder, config.runtime.decode_group);
        let ended = Mutex::new(VecDeque::with_capacity(KEEP_ENDED));
        let surfaces = m
            .objects
            .iter()
            .map(|o| {
                let bytes = bundle.file_bytes(&o.mesh)?;
                let path = bundle.origin().path_of(&o.mesh);
                let text = std::str::from_utf8(&bytes).map_err(|_| Error::bundle(&path, "mesh is not UTF-8 text"))?;
                let mesh = crate::bundle::obj::parse(text).map_err(|e| Error::bundle(&path, e))?;
                Ok(Arc::new(ObjectSurface::from_mesh(&mesh)))
            })
            .collect::<Result<Vec<_>>>()?;
        let embeddings = Mutex::new(VecDeque::with_capacity(KEEP_EMBEDDINGS));
        Ok(Pipeline { end_ids: m.end_ids(), pad_ids, assembler, bundle, overlap, group, ended, surfaces, embeddings })
    }

    /// A fresh contact-consistency stage for catalogue object `index` (its box and the
    /// surface of its mesh), as a stream on this pipeline runs it.
    pub fn contact_stage(&self, index: usize) -> ContactStage {
        let shape = ObjectShape::from_entry(&self.bundle.manifest.objects[index]);
        ContactStage::new(shape.with_surface(Arc::clone(&self.surfaces[index])), self.bundle.manifest.fps)
    }

    /// The text embedding of `text`: kept from an earlier stream with the same prompt (the
    /// same bits: the encoder is deterministic), else encoded now (outside the lock) and
    /// kept, the least recently used prompt forgotten first.
    pub fn embedding(&self, text: &str) -> Result<Arc<[f32]>> {
        let found = |kept: &mut VecDeque<(String, Arc<[f32]>)>| {
            let i = kept.iter().position(|(t, _)| t == text)?;
            let entry = kept.remove(i)?;
            let emb = Arc::clone(&entry.1);
            kept.push_back(entry);
            Some(emb)
        };
        if let Some(e) = found(&mut self.embeddings.lock()) {
            return Ok(e);
        }
        let emb: Arc<[f32]> = self.bundle.text.embed(text)?.into();
        let mut kept = self.embeddings.lock();
        if let Some(e) = found(&mut kept) {
            return Ok(e);
        }
        if kept.len() == KEEP_EMBEDDINGS {
            kept.pop_front();
        }
        kept.push_back((text.to_owned(), Arc::clone(&emb)));
        Ok(emb)
    }

    fn continuation(&self, id: u64) -> Option<Arc<Continuation>> {
        self.ended.lock().iter().find(|(i, _)| *i == id).map(|(_, c)| Arc::clone(c))
    }

    /// Keeps an ended stream's state. Allocation-free: the entry was made when the stream
    /// started and the queue's capacity is fixed.
    fn remember(&self, id: u64, c: Arc<Continuation>) {
        let mut ended = self.ended.lock();
        if ended.len() == KEEP_ENDED {
            ended.pop_front();
        }
        ended.push_back((id, c));
    }

    /// The bundle the pipeline runs.
    pub fn bundle(&self) -> &Arc<Bundle> {
        &self.bundle
    }

    /// Whether some stream sampled its End id (the sequence ends at that step).
    fn ends(&self, codes: &[usize; N_STREAMS]) -> bool {
        codes.iter().zip(&self.end_ids).any(|(c, e)| c == e)
    }

    /// The frame assembler every stream of this pipeline uses.
    pub fn assembler(&self) -> &FrameAssembler {
        &self.assembler
    }

    /// Whether streams run step k+1 with the decode of chunk k (`model::overlap`).
    pub fn overlap(&self) -> bool {
        self.overlap
    }

    /// The same pipeline with overlap on or off (the tokens and frames are the same either
    /// way; on models that cannot overlap, "on" runs the two one after the other).
    pub fn with_overlap(mut self, on: bool) -> Pipeline {
        self.overlap = on;
        self
    }

    /// Tokens a stream decodes at once after its first chunk (`model::decode_group`).
    pub fn group(&self) -> usize {
        self.group
    }

    /// The same pipeline decoding `tokens` at once (clamped to 1 ..= `MAX_DECODE_GROUP`;
    /// the tokens and frames are the same for every value).
    pub fn with_group(mut self, tokens: usize) -> Pipeline {
        self.group = tokens.clamp(1, MAX_DECODE_GROUP);
        self
    }
}

/// One stream's generation state (KV cache, decoder context, sampler, held frame).
pub struct Generator {
    pipe: Arc<Pipeline>,
    stream_id: u64,
    text: String,
    /// Computed on the worker by the first `next_chunk`.
    text_emb: Option<Arc<[f32]>>,
    sampler: TokenSampler,
    /// Classifier-free guidance scale (1 = the prompt alone).
    guidance: f32,
    max_len: usize,
    /// KV cache, decoder context and the decode buffer: made by the first `next_chunk`,
    /// on the worker, so `cg_start` never pays for allocating and zeroing them.
    state: Option<State>,
    /// Next step index k.
    k: usize,
    /// Codes sampled at step k-1 (the Pad ids before step 0).
    prev: [i64; N_STREAMS],
    /// The final frame of the previous chunk, waiting for the next step's verdict.
    held: Option<Frame>,
    /// The held frame's pose, for the contact stage's last word on the stream's last frame.
    held_pose: Pose,
    /// Codes of steps k, k+1, ..., sampled during the previous call's decode (overlap):
    /// `ahead[..ahead_n]`; `ahead_end`: the sequence ends after them.
    ahead: [[i64; N_STREAMS]; MAX_DECODE_GROUP],
    ahead_n: usize,
    ahead_end: bool,
    next_frame: u64,
    done: bool,
    /// The contact-consistency stage (None: the raw model output was asked for).
    contact: Option<ContactStage>,
    /// Placement from the grasp (`contact::GraspOnset`): while it is undecided, decoded
    /// frames are held back in the decode buffer (`pending` values at its start).
    onset: Option<GraspOnset>,
    pending: usize,
    /// Where the first frame's object goes once decided (None: where the model put it).
    placement: Option<Vec3>,
    /// Scene anchoring (None: the model's own placement).
    anchor: Option<AnchorStage>,
    object: StreamObject,
    /// The earlier stream this one continues, and its last pose in this stream's model frame
    /// (set by the first frame) that the body blends from.
    continuation: Option<Arc<Continuation>>,
    blend_from: Option<Pose>,
    /// Where this stream leaves off, made at the start (the end must not allocate).
    memo: Option<Arc<Continuation>>,
}

impl Generator {
    /// Sets up one generation: resolves and validates the sampling settings (stream, then
    /// engine, then bundle defaults). Cheap: no inference and no model state here.
    pub fn new(pipe: Arc<Pipeline>, req: &StreamRequest<'_>) -> Result<Generator> {
        let b = &pipe.bundle;
        let d = &b.manifest.sampling;
        let l_max = b.manifest.l_max as u32;
        let c = req.config;
        let default_max = if d.max_len == 0 { l_max } else { d.max_len as u32 };
        let params = SamplingParams::new(
            c.temperature.unwrap_or(d.temperature),
            c.top_k.unwrap_or(d.top_k as u32),
            c.min_len.unwrap_or(d.min_len as u32),
            c.max_len.unwrap_or(default_max),
            l_max,
        )?;
        if params.max_len == 0 {
            return Err(Error::InvalidArgument("max_len must be at least 1".into()));
        }
        let guidance = guidance_scale(c.guidance.unwrap_or(d.guidance))?;
        let pad_usize = pipe.pad_ids.map(|p| p as usize);
        let continuation = match c.continue_from {
            None => None,
            Some(_) if c.anchor.is_some() => {
                return Err(Error::InvalidArgument(
                    "continue_from and anchor exclude each other: a continued stream starts where the earlier one \
                     left off"
                        .into(),
                ))
            }
            Some(id) => Some(pipe.continuation(id).ok_or_else(|| {
                Error::InvalidArgument(format!(
                    "continue_from: stream {id} has not ended on this engine (or is older than its last {KEEP_ENDED} \
                     ended streams)"
                ))
            })?),
        };
        // The catalogue is never empty (bundle verification). A continued stream keeps the
        // earlier stream's object, whatever its prompt names.
        let objects = &b.manifest.objects;
        let object = match &continuation {
            Some(k) => k.object.clone(),
            None => {
                let (index, alias) = choose_object(objects, req.text)
                    .ok_or_else(|| Error::InvalidArgument("the bundle's object catalogue is empty".into()))?;
                StreamObject { index, name: objects[index].name.clone(), alias }
            }
        };
        let contact = match (c.raw_output.unwrap_or(false), c.foot_lock.unwrap_or(true)) {
            (true, _) => None,
            (false, true) => Some(pipe.contact_stage(object.index)),
            (false, false) => Some(pipe.contact_stage(object.index).with_free_feet()),
        };
        let anchor = match &continuation {
            Some(k) => {
                let p = &k.pose;
                Some(AnchorStage::continuing(k.ground, heading(&p.pelvis, &p.local[0], &p.object_centre)))
            }
            None => c.anchor.as_ref().map(|a| AnchorStage::new(a, pipe.assembler.coordinate_system())).transpose()?,
        };
        // A continued stream's object is where the earlier one left it, an anchored one's
        // where the host put it: nothing to place.
        let place = contact.is_some()
            && c.grasp_placement.unwrap_or(true)
            && continuation.is_none()
            && !anchor.as_ref().is_some_and(AnchorStage::fixes_object);
        let sampler = TokenSampler::new(c.seed.unwrap_or(d.seed), params, pipe.end_ids, pad_usize);
        let memo = Arc::new(Continuation {
            pose: Pose::default(),
            contact: contact.clone(),
            ground: [0.0; 3],
            object: object.clone(),
        });
        Ok(Generator {
            stream_id: req.stream_id,
            text: req.text.to_owned(),
            text_emb: None,
            max_len: params.max_len as usize,
            guidance,
            state: None,
            k: 0,
            prev: pipe.pad_ids,
            held: None,
            held_pose: Pose::default(),
            ahead: [[0; N_STREAMS]; MAX_DECODE_GROUP],
            ahead_n: 0,
            ahead_end: false,
            next_frame: 0,
            done: false,
            contact,
            onset: place.then(GraspOnset::default),
            pending: 0,
            placement: None,
            anchor,
            object,
            memo: Some(memo),
            continuation,
            blend_from: None,
            sampler,
            pipe,
        })
    }

    /// The prompt's embedding, on the first step (from the pipeline's kept prompts).
    fn encode_text(&mut self) -> Result<()> {
        if self.text_emb.is_none() {
            self.text_emb = Some(self.pipe.embedding(&self.text)?);
        }
        Ok(())
    }

    /// Runs step `k` on the codes of step `k - 1` and samples its codes; `None` when the
    /// sequence ends at `k`.
    fn sample(&mut self, k: usize, prev: [i64; N_STREAMS]) -> Result<Option<[i64; N_STREAMS]>> {
        self.encode_text()?;
        let b = &self.pipe.bundle;
        let emb = self.text_emb.as_deref().unwrap_or_default();
        let state = self.state.get_or_insert_with(|| State::new(b, self.guidance, self.onset.is_some()));
        let logits = b.step.step(&mut state.step, prev, k, emb)?;
        let codes = self.sampler.sample_step(k, logits)?;
        if self.pipe.ends(&codes) {
            return Ok(None);
        }
        Ok(Some(codes.map(|c| c as i64)))
    }
}

impl Generator {
    /// The first frame: fixes the anchoring; a continued stream takes over the earlier
    /// stream's last pose (to blend from) and contact state, moved into its model frame.
    fn begin(&mut self, pose: &Pose) {
        let Some(anchor) = &mut self.anchor else { return };
        let start = anchor.begin(pose);
        match (&self.continuation, anchor.world()) {
            (Some(k), Some((r, t))) => {
                // The inverse of the world motion: the host's world -> this model frame.
                let ri = transpose(&r);
                let ti = mat_vec(&ri, &t).map(|v| -v);
                let mut from = k.pose;
                from.transform(&ri, &ti);
                self.blend_from = Some(from);
                if let (Some(stage), Some(earlier)) = (&mut self.contact, &k.contact) {
                    *stage = earlier.continued(&ri, &ti).with_settings_of(stage);
                }
            }
            _ => {
                if let (Some((rot, pos)), Some(stage)) = (start, &mut self.contact) {
                    stage.set_start_object(rot, pos);
                }
            }
        }
    }

    /// The last frame (`pose` in the host's world): what a stream continuing this one needs.
    fn remember(&mut self, pose: &Pose) {
        let (r, t): (Mat3, Vec3) =
            self.anchor.as_ref().and_then(AnchorStage::world).unwrap_or((crate::skeleton::IDENTITY, [0.0; 3]));
        let Some(mut memo) = self.memo.take() else { return };
        // Only this stream holds the entry until it is handed to the pipeline.
        if let Some(m) = Arc::get_mut(&mut memo) {
            m.pose = *pose;
            m.ground = [pose.pelvis[0], pose.pelvis[1], t[2]];
            if let (Some(slot), Some(stage)) = (&mut m.contact, &self.contact) {
                *slot = stage.continued(&r, &t);
            }
        }
        self.pipe.remember(self.stream_id, memo);
    }
}

/// The per-stream model state.
struct State {
    step: StepState,
    decoder: DecoderState,
    /// The normalized output of one decode (up to MAX_DECODE_GROUP x F x 335), after the
    /// frames held back for the look-ahead (`lookahead`: room for PLACE_LOOKAHEAD more), reused.
    normalized: Vec<f32>,
}

impl State {
    fn new(b: &Bundle, guidance: f32, lookahead: bool) -> State {
        let extra = if lookahead { PLACE_LOOKAHEAD.div_ceil(b.manifest.frames_per_token) } else { 0 };
        let normalized = vec![0.0; (MAX_DECODE_GROUP + extra) * b.decoder.chunk_len()];
        State { step: b.step.new_guided_state(guidance), decoder: b.decoder.new_state(), normalized }
    }
}

impl ChunkSource for Generator {
    /// A decode's chunks plus the previous call's held frame.
    fn max_chunk_frames(&self) -> usize {
        let held_back = if self.onset.is_some() { PLACE_LOOKAHEAD } else { 0 };
        self.pipe.group * self.pipe.bundle.manifest.frames_per_token + 1 + held_back
    }

    fn object(&self) -> Option<StreamObject> {
        Some(self.object.clone())
    }

    fn next_chunk(&mut self, out: &mut Vec<Frame>) -> Result<bool> {
        if self.done {
            return Ok(false);
        }
        // The tokens of this decode: those sampled during the previous call's decode
        // (overlap), else step k's, sampled now.
        let mut group = [[0i64; N_STREAMS]; MAX_DECODE_GROUP];
        let mut g = self.ahead_n;
        // whether the sequence ends after the group's codes
        let mut ended = self.ahead_end;
        if g > 0 {
            group[..g].copy_from_slice(&self.ahead[..g]);
            self.ahead_n = 0;
        } else {
            let codes = if self.k >= self.max_len { None } else { self.sample(self.k, self.prev)? };
            let Some(codes) = codes else {
                self.release_last(out);
                return Ok(false);
            };
            if let Some(f) = self.held.take() {
                out.push(f);
            }
            group[0] = codes;
            g = 1;
        }
        // The group is topped up to its size with the next steps, run now.
        let want = decode_group::tokens_at(self.k, self.pipe.group);
        while !ended && g < want && self.k + g < self.max_len {
            match self.sample(self.k + g, group[g - 1])? {
                Some(codes) => {
                    group[g] = codes;
                    g += 1;
                }
                None => ended = true,
            }
        }
        let next = self.k + g;
        ended |= next >= self.max_len;
        let b = &self.pipe.bundle;
        let state = self.state.get_or_insert_with(|| State::new(b, self.guidance, self.onset.is_some()));
        let normalized = &mut state.normalized[self.pending..self.pending + g * b.decoder.chunk_len()];
        // Whether the group's last chunk ends the sequence: known now if End was sampled or
        // the step limit forces it, or once the steps after the group ran with the decode
        // (overlap); otherwise the next call decides.
        let last = if ended {
            b.decoder.decode_group(&mut state.decoder, &group[..g], normalized)?;
            Some(true)
        } else if self.pipe.overlap {
            // the next group's steps run on one thread while the decoder's jobs run on both:
            // as many as this group has tokens (one with the first chunk, so the first
            // frame waits for no more)
            let steps = want.min(self.max_len - next);
            let emb = self.text_emb.as_deref().unwrap_or_default();
            let (sampler, pipe) = (&mut self.sampler, &self.pipe);
            let sample = |pos: usize, logits: [&[f32]; N_STREAMS]| -> Result<Option<[i64; N_STREAMS]>> {
                let codes = sampler.sample_step(pos, logits)?;
                Ok(if pipe.ends(&codes) { None } else { Some(codes.map(|c| c as i64)) })
            };
            let (n, end) = overlap::decode_and_steps(
                &b.decoder,
                &mut state.decoder,
                &group[..g],
                normalized,
                &b.step,
                &mut state.step,
                next,
                emb,
                &mut self.ahead[..steps],
                sample,
                true,
            )?;
            self.ahead_n = n;
            self.ahead_end = end || next + n >= self.max_len;
            Some(n == 0)
        } else {
            b.decoder.decode_group(&mut state.decoder, &group[..g], normalized)?;
            None
        };
        let used = normalized.len();
        self.emit_group(used, last, out);
        self.prev = group[g - 1];
        self.k = next;
        Ok(last != Some(true))
    }
}

impl Generator {
    /// The previous chunk was the last one: releases its held frame, marked, and ends.
    fn release_last(&mut self, out: &mut Vec<Frame>) {
        if self.pending > 0 {
            // Frames held back for the look-ahead: they go out now, the last one marked.
            self.emit_group(0, Some(true), out);
            return;
        }
        self.done = true;
        if let Some(mut f) = self.held.take() {
            // The contact stage's last word (an object still falling lands), then the same
            // frame again, marked.
            let assembler = &self.pipe.assembler;
            let mut pose = self.held_pose;
            if let Some(stage) = &mut self.contact {
                stage.finish(assembler.skeleton(), &mut pose);
            }
            if let Some(anchor) = &self.anchor {
                anchor.apply(&mut pose);
            }
            assembler.emit(&pose, f.stream_id, f.frame_index, true, &mut f);
            self.remember(&pose);
            out.push(f);
        }
    }

    /// Assembles the `used` values the decode just wrote (whole frames, after any held back)
    /// into frames: `last`: whether the group's last chunk ends the sequence (`None`: not
    /// known yet, its final frame is held for the next step's verdict). While the grasp
    /// look-ahead is undecided, the frames are held back instead.
    fn emit_group(&mut self, used: usize, last: Option<bool>, out: &mut Vec<Frame>) {
        let Some(state) = self.state.as_mut() else { return };
        let width = crate::bundle::manifest::FRAME_DIM;
        // Moved out (no copy, no allocation) so the frame loop may borrow the generator.
        let buffer = std::mem::take(&mut state.normalized);
        let used = self.pending + used;
        if let Some(onset) = &mut self.onset {
            if !onset.feed_features(&self.pipe.assembler, &buffer[self.pending..used]) && last != Some(true) {
                self.pending = used;
                state.normalized = buffer;
                return;
            }
            self.placement = onset.centre();
            (self.onset, self.pending) = (None, 0);
        }
        let n = used / width;
        let pipe = Arc::clone(&self.pipe);
        for (i, feats) in buffer[..used].chunks_exact(width).enumerate() {
            let mut frame = Frame::default();
            let last_of_chunk = i + 1 == n;
            let is_last = last_of_chunk && last == Some(true);
            let assembler = &pipe.assembler;
            let mut pose = Pose::default();
            assembler.decode(feats, &mut pose);
            if let Some(stage) = &mut self.contact {
                stage.ground(assembler.skeleton(), &mut pose);
            }
            if self.next_frame == 0 {
                if let (Some(centre), Some(stage)) = (self.placement, &self.contact) {
                    stage.place(&mut pose, &centre);
                }
                self.begin(&pose);
            }
            if let Some(from) = &self.blend_from {
                if self.next_frame < BLEND_FRAMES {
                    pose.blend_from(from, smoothstep((self.next_frame + 1) as f64 / (BLEND_FRAMES + 1) as f64));
                    // The model does not know it holds the object: the hands keep it while
                    // they blend.
                    if let Some(stage) = &self.contact {
                        for (c, held) in pose.contact.iter_mut().zip(stage.holding()) {
                            *c |= held;
                        }
                    }
                }
            }
            if let Some(stage) = &mut self.contact {
                stage.apply(assembler.skeleton(), &mut pose);
                if is_last {
                    stage.finish(assembler.skeleton(), &mut pose);
                }
            }
            // The held frame keeps its pose in the model's frame (finish may change it).
            let model_pose = pose;
            if let Some(anchor) = &self.anchor {
                anchor.apply(&mut pose);
            }
            assembler.emit(&pose, self.stream_id, self.next_frame, is_last, &mut frame);
            if is_last {
                self.remember(&pose);
            }
            self.next_frame += 1;
            if last_of_chunk && last.is_none() {
                self.held = Some(frame);
                self.held_pose = model_pose;
            } else {
                out.push(frame);
            }
        }
        if let Some(state) = &mut self.state {
            state.normalized = buffer;
        }
        if last == Some(true) {
            self.done = true;
        }
    }
}

/// What a generation needs next when the crowd scheduler drives it (`crate::crowd`)
/// instead of [`ChunkSource::next_chunk`]: the same tokens and frames, one step per round.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Need {
    /// A token step ([`Generator::step_job`], then [`Generator::sampled`]).
    Step,
    /// A decode of the tokens gathered ([`Generator::decode`]).
    Decode,
    /// The end: the held frame goes out marked ([`Generator::finish`]).
    Finish,
    /// Nothing more.
    Done,
}

impl Generator {
    /// What this generation needs next. The group of tokens a decode takes fills up in
    /// `ahead`, one token per round: 1 for the first chunk, then the pipeline's group.
    pub fn need(&self) -> Need {
        if self.done {
            Need::Done
        } else if self.ahead_end || self.ahead_n == decode_group::tokens_at(self.k, self.pipe.group) {
            Need::Decode
        } else if self.k + self.ahead_n < self.max_len {
            Need::Step
        } else if self.ahead_n > 0 {
            // the step limit: the group decodes as it is, as the last one
            Need::Decode
        } else {
            Need::Finish
        }
    }

    /// The token step this generation needs ([`Need::Step`]), checked: the first one
    /// encodes the text and makes the model state.
    pub(crate) fn step_job(&mut self) -> Result<StepJob<'_>> {
        self.encode_text()?;
        let pipe = Arc::clone(&self.pipe);
        let j = self.job();
        pipe.bundle.step.check(j.state, j.tokens, j.pos, j.text_emb)?;
        Ok(j)
    }

    /// [`step_job`](Self::step_job) again, once it passed (unchecked).
    pub(crate) fn job(&mut self) -> StepJob<'_> {
        let b = &self.pipe.bundle;
        let pos = self.k + self.ahead_n;
        let tokens = if self.ahead_n > 0 { self.ahead[self.ahead_n - 1] } else { self.prev };
        let text_emb = self.text_emb.as_deref().unwrap_or_default();
        let state = &mut self.state.get_or_insert_with(|| State::new(b, self.guidance, self.onset.is_some())).step;
        StepJob { state, tokens, pos, text_emb }
    }

    /// Samples the step [`step_job`](Self::step_job) gave, once it ran: the token joins
    /// the group, or the sequence ends. The first token after a decode decides the held
    /// frame: it goes out into `out`, marked last if the sequence ended.
    pub fn sampled(&mut self, out: &mut Vec<Frame>) -> Result<()> {
        let pos = self.k + self.ahead_n;
        let state = self.state.as_ref().ok_or_else(|| Error::WrongState("no step ran".into()))?;
        let codes = self.sampler.sample_step(pos, state.step.logits())?;
        if self.pipe.ends(&codes) {
            if self.ahead_n == 0 {
                self.release_last(out);
            } else {
                self.ahead_end = true;
            }
            return Ok(());
        }
        if self.ahead_n == 0 {
            out.extend(self.held.take());
        }
        self.ahead[self.ahead_n] = codes.map(|c| c as i64);
        self.ahead_n += 1;
        Ok(())
    }

    /// Decodes the gathered tokens ([`Need::Decode`]) into `out`, the final frame held
    /// unless the sequence is known to end with them. `team`: the decoder may use its
    /// helper thread. The same bits either way.
    pub fn decode(&mut self, team: bool, out: &mut Vec<Frame>) -> Result<()> {
        let pipe = Arc::clone(&self.pipe);
        let j = self.decode_job()?;
        pipe.bundle.decoder.decode_checked(j.state, j.tokens, j.out, None, team)?;
        self.decoded(out);
        Ok(())
    }

    /// The decode this generation needs ([`Need::Decode`]), checked; after it ran,
    /// [`decoded`](Self::decoded).
    pub(crate) fn decode_job(&mut self) -> Result<DecodeJob<'_>> {
        if self.ahead_n == 0 {
            return Err(Error::WrongState("no tokens to decode".into()));
        }
        let pipe = Arc::clone(&self.pipe);
        let j = self.decode_job_unchecked();
        pipe.bundle.decoder.check(j.state, j.tokens, j.out)?;
        Ok(j)
    }

    /// [`decode_job`](Self::decode_job) again, once it passed.
    pub(crate) fn decode_job_unchecked(&mut self) -> DecodeJob<'_> {
        let b = &self.pipe.bundle;
        let state = self.state.get_or_insert_with(|| State::new(b, self.guidance, self.onset.is_some()));
        let g = self.ahead_n;
        let out = &mut state.normalized[self.pending..self.pending + g * b.decoder.chunk_len()];
        DecodeJob { state: &mut state.decoder, tokens: &self.ahead[..g], out }
    }

    /// The frames of the decode [`decode_job`](Self::decode_job) gave, once it ran, into
    /// `out`.
    pub(crate) fn decoded(&mut self, out: &mut Vec<Frame>) {
        let g = self.ahead_n;
        let next = self.k + g;
        let ended = self.ahead_end || next >= self.max_len;
        self.emit_group(g * self.pipe.bundle.decoder.chunk_len(), ended.then_some(true), out);
        self.prev = self.ahead[g - 1];
        self.k = next;
        (self.ahead_n, self.ahead_end) = (0, false);
    }

    /// The end ([`Need::Finish`]): the held frame goes out into `out`, marked last.
    pub fn finish(&mut self, out: &mut Vec<Frame>) {
        self.release_last(out);
    }

    /// The pipeline this generation runs on.
    pub fn pipeline(&self) -> &Arc<Pipeline> {
        &self.pipe
    }
}
