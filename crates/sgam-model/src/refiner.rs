//! [`VqRefiner`]: the learned [`Refiner`] the generator calls (guidance in, complete frame out).
//!
//! Weight files are safetensors keyed by parameter path; the model config travels in the file's
//! metadata under [`CONFIG_METADATA_KEY`] (JSON), or as a separate JSON file.

use std::collections::HashMap;
use std::path::Path;

use burn::module::Module;
use burn::tensor::{Device, Int, Tensor, TensorData};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sgam_core::{Guidance, Image, Intrinsics, Refiner, RgbdFrame};

use crate::bank::{BankDraw, BankFill, BankPixels, BankSearch, CodeBank, FillHints, Pasted};
use crate::config::ModelConfig;
use crate::context::{CellState, ContextInput};
use crate::model::VqModel;
use crate::nhwc::NhwcNet;
use crate::packing::{missing_cells, pack_input, pack_input_values, unpack, unpack_values};
use crate::params::{from_safetensors_bytes, load_named, save_safetensors, WeightPrecision};
use crate::quantize::{select_codes, select_codes_by_class, squared_distances, to_host, Sampling};
use crate::ModelError;

/// Safetensors metadata key holding the [`ModelConfig`] JSON.
pub const CONFIG_METADATA_KEY: &str = "sgam_model_config";

/// What a [`ModelError::Format`] error of a config file given beside the weights names.
const CONFIG_JSON: &str = "the config JSON";

/// Metadata map carrying `config`.
pub fn weight_metadata(config: &ModelConfig) -> Result<HashMap<String, String>, ModelError> {
    let json = serde_json::to_string(config).map_err(|e| ModelError::state("the model config", e))?;
    Ok(HashMap::from([(CONFIG_METADATA_KEY.to_string(), json)]))
}

/// Saves a model with its config embedded (f16 halves the size; used for the shipped model).
pub fn save_model(
    model: &VqModel,
    config: &ModelConfig,
    path: &Path,
    precision: WeightPrecision,
) -> Result<(), ModelError> {
    save_safetensors(model, path, precision, Some(weight_metadata(config)?))
}

/// Loads a model from safetensors bytes; the config comes from `config_json` when given, else
/// from the file's metadata.
pub fn load_model_bytes(
    weights: &[u8],
    config_json: Option<&[u8]>,
    device: &Device,
) -> Result<(VqModel, ModelConfig), ModelError> {
    let (tensors, meta) = from_safetensors_bytes(weights)?;
    let config: ModelConfig = match config_json {
        Some(json) => {
            serde_json::from_slice(json).map_err(|e| ModelError::Format { what: CONFIG_JSON, msg: e.to_string() })?
        }
        None => {
            let json = meta.get(CONFIG_METADATA_KEY).ok_or_else(|| ModelError::MissingPart {
                part: "a config (no 'sgam_model_config' metadata in the weights, and none given)",
                operation: "loading weights",
            })?;
            serde_json::from_str(json)
                .map_err(|e| ModelError::Format { what: "the embedded config", msg: e.to_string() })?
        }
    };
    let model = load_named(VqModel::new(&config, 0, device)?, &tensors, false, false)?;
    Ok((model, config))
}

/// Loads a model from a safetensors file and an optional config JSON file.
pub fn load_model(
    weights: &Path,
    config: Option<&Path>,
    device: &Device,
) -> Result<(VqModel, ModelConfig), ModelError> {
    let bytes = std::fs::read(weights).map_err(|e| ModelError::io(weights, e))?;
    let cfg = match config {
        Some(p) => Some(std::fs::read(p).map_err(|e| ModelError::io(p, e))?),
        None => None,
    };
    load_model_bytes(&bytes, cfg.as_deref(), device).map_err(|e| match (&e, config) {
        (ModelError::Format { what: CONFIG_JSON, .. }, Some(p)) => e.in_file(p),
        _ => e.in_file(weights),
    })
}

/// Sampling options of the refiner.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RefinerOptions {
    /// Code selection (argmin, or temperature + top-k in missing cells).
    pub sampling: Sampling,
    /// Seed of the sampling RNG.
    pub seed: u64,
    /// A latent cell counts as missing when more than this fraction of its pixels is missing.
    pub missing_cell_threshold: f32,
    /// Keep the guidance where it was observed and use the model's output only in missing
    /// pixels (default). The paper's model regenerates every pixel, which drifts the observed
    /// part of the frame away from the map; `false` reproduces that behaviour.
    #[serde(default = "default_true")]
    pub keep_observed: bool,
    /// Iterative sampling: missing latent cells drawn per pass (see [`VqRefiner::complete_at`]).
    #[serde(default = "default_cells_per_pass")]
    pub cells_per_pass: usize,
    /// Iterative sampling: at most this many encode/decode passes per frame.
    #[serde(default = "default_max_passes")]
    pub max_passes: usize,
    /// Two-level sampling (see [`crate::quantize::select_codes_by_class`]): a missing cell's
    /// class (plain = grey ground codes, or coloured) is drawn at the sampling temperature, its
    /// code within the class at this temperature (same units). `None`: plain temperature
    /// sampling.
    #[serde(default)]
    pub within_class_temperature: Option<f32>,
    /// With a code bank: a bank object that observed ground would cut is left out of the hole
    /// ([`crate::bank::BankSearch::whole_objects`]).
    #[serde(default)]
    pub whole_objects: bool,
    /// With a seed's pixel bank: holes larger than this many cells a side are quilted as tiles
    /// of this side ([`crate::bank::BankSearch::tile`]); 0, as runs made before it, quilts a
    /// hole in one piece.
    #[serde(default)]
    pub quilt_tile: usize,
    /// A hole along the frame's border that reaches fewer than this many latent cells into the
    /// frame waits: its pixels keep a provisional colour and no depth, so nothing is fused there,
    /// and it widens step by step until a whole object fits (filled at once, it would commit a
    /// sliver of whatever it holds, and the next step would have to continue a sliver). 0 fills
    /// every hole. `None`: [`DEFAULT_BANDS_WAIT`] for a code bank's holes
    /// ([`crate::bank::BankSearch::defer_thinner_than`]), 0 for the model's own draws (waiting
    /// grew larger mounds there: docs/MODEL.md, session 29).
    #[serde(default)]
    pub bands_wait: Option<usize>,
    /// Hue coherence of the context's draws (0 = off): with two-level sampling, a missing cell
    /// drawing a coloured code next to cells already coloured (observed, or drawn in an earlier
    /// pass) pays up to this much for a code whose hue turns away from theirs
    /// (`hue_coherence * (1 - cos angle) / 2`), in the draw within the class only, so an object
    /// keeps one colour across its cells; how often cells start objects is unchanged. In the
    /// logits' units, before the within-class temperature divides them (3 at 0.6 is 5 nats).
    #[serde(default)]
    pub hue_coherence: f32,
    /// Class coherence of the context's draws (0 = off): with two-level sampling, a missing
    /// cell's odds of drawing a coloured code rather than a plain one move by up to this many
    /// logits towards the class its decided 4-neighbours hold (observed, or drawn in an earlier
    /// pass): `strength * (coloured - plain) / decided`. An experiment (docs/MODEL.md, session
    /// 31): smoother ground, fewer objects, KID either way.
    #[serde(default)]
    pub class_coherence: f32,
}

/// [`RefinerOptions::bands_wait`] for a code bank's holes when not given (docs/MODEL.md, session
/// 16: 3 against 5 cells).
pub const DEFAULT_BANDS_WAIT: usize = 3;

fn default_cells_per_pass() -> usize {
    48
}

/// [`RefinerOptions::max_passes`] by default (session 10).
pub const DEFAULT_MAX_PASSES: usize = 4;

/// A code's mean chroma (colour units, 0-1) below which it has no hue
/// ([`VqRefiner::code_hues`]): its colours cancel out.
pub const MIN_HUE_CHROMA: f32 = 0.05;

fn default_max_passes() -> usize {
    DEFAULT_MAX_PASSES
}

fn default_true() -> bool {
    true
}

impl Default for RefinerOptions {
    fn default() -> Self {
        Self {
            sampling: Sampling::Argmin,
            seed: 0,
            missing_cell_threshold: 0.5,
            keep_observed: true,
            cells_per_pass: default_cells_per_pass(),
            max_passes: default_max_passes(),
            within_class_temperature: None,
            whole_objects: false,
            quilt_tile: 0,
            bands_wait: None,
            hue_coherence: 0.0,
            class_coherence: 0.0,
        }
    }
}

/// The learned refiner: packs the guidance, encodes, quantizes (sampling in missing cells),
/// decodes and unpacks. Inputs of any size are padded (as missing) to a multiple of the
/// downsampling factor and the output cropped back.
#[derive(Debug)]
pub struct VqRefiner {
    model: VqModel,
    config: ModelConfig,
    options: RefinerOptions,
    rng: ChaCha8Rng,
    device: Device,
    trace: SamplingTrace,
    plain_codes: Option<Vec<bool>>,
    /// Per code, the unit chroma direction of its patch (zero for plain codes), computed once
    /// for [`RefinerOptions::hue_coherence`].
    code_hues: Option<Vec<[f32; 2]>>,
    /// Completion by quilting from true frames' codes ([`crate::bank`]) instead of sampling.
    bank: Option<std::sync::Arc<CodeBank>>,
    /// Per code: mean colour and normalised disparity of its decoded patch ([`Self::code_looks`]).
    looks: Option<Vec<[f32; 4]>>,
    /// The pixels behind the bank's codes: holes take them instead of the decoder's output.
    bank_pixels: Option<std::sync::Arc<BankPixels>>,
    /// With the bank's pixels: holes take only their depth, and their colour is the decoder's
    /// drawing of the quilted codes (a decoder adapted to the seed).
    bank_colour_from_decoder: bool,
    /// The encoder and decoder in the CPU kernels ([`crate::nhwc`]): present on the CPU backend
    /// for a model they cover (no attention).
    nhwc: Option<NhwcNet>,
    /// Whether passes use [`Self::nhwc`] (on by default; off runs burn's path, for comparison).
    use_nhwc: bool,
}

/// What the last [`VqRefiner::complete_at`] call chose (for tests and diagnostics).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SamplingTrace {
    /// The code of every latent cell, row-major.
    pub codes: Vec<u32>,
    /// The missing cells committed in each pass, in commit order.
    pub passes: Vec<Vec<usize>>,
    /// Latent cells that were missing.
    pub missing_cells: Vec<bool>,
    /// Tokens the context transformer saw in each pass (empty without a context).
    pub context_tokens: Vec<usize>,
    /// How the code bank filled each hole (empty without a bank).
    pub bank_draws: Vec<BankDraw>,
}

impl VqRefiner {
    /// Wraps a model.
    pub fn new(model: VqModel, config: ModelConfig, options: RefinerOptions, device: Device) -> Self {
        Self::with_kernels(model, config, options, device, !cfg!(feature = "wgpu"))
    }

    /// Loads `weights` on the CPU backend with the model's CPU kernels, in any build: what many
    /// threads at once run best (closed-loop pair recording, whose runs would otherwise queue
    /// on one GPU in a `wgpu` build).
    pub fn from_bytes_cpu(
        weights: &[u8],
        config_json: Option<&[u8]>,
        options: RefinerOptions,
    ) -> Result<Self, ModelError> {
        let device = Device::flex();
        let (model, config) = load_model_bytes(weights, config_json, &device)?;
        Ok(Self::with_kernels(model, config, options, device, true))
    }

    fn with_kernels(model: VqModel, config: ModelConfig, options: RefinerOptions, device: Device, cpu: bool) -> Self {
        let rng = ChaCha8Rng::seed_from_u64(options.seed);
        let model = model.valid();
        // the CPU kernels on the CPU backend; a model they do not cover (attention) keeps burn's
        // path, and so does one whose weights they cannot take, said aloud: it runs several
        // times slower
        let nhwc = if !cpu {
            None
        } else {
            NhwcNet::new(&model, &config).unwrap_or_else(|e| {
                eprintln!("warning: the model's CPU kernels cannot take its weights ({e}); it runs in burn, slower");
                None
            })
        };
        Self {
            model,
            config,
            options,
            rng,
            device,
            trace: SamplingTrace::default(),
            plain_codes: None,
            code_hues: None,
            bank: None,
            looks: None,
            bank_pixels: None,
            bank_colour_from_decoder: false,
            nhwc,
            use_nhwc: true,
        }
    }

    /// Runs the encoder and decoder in the CPU kernels ([`crate::nhwc`], the default where they
    /// cover the model) or in burn (`false`; for comparisons: both compute the same pass).
    pub fn set_cpu_kernels(&mut self, on: bool) {
        self.use_nhwc = on;
    }

    /// Whether passes run in the CPU kernels.
    pub fn uses_cpu_kernels(&self) -> bool {
        self.use_nhwc && self.nhwc.is_some()
    }

    fn cpu_net(&self) -> Option<&NhwcNet> {
        self.nhwc.as_ref().filter(|_| self.use_nhwc)
    }

    /// The encoder's features of `frame` with `mask` in the CPU kernels (no burn tensor).
    fn cpu_features(
        &self,
        net: &NhwcNet,
        frame: &RgbdFrame,
        mask: &[bool],
        intrinsics: &Intrinsics,
    ) -> Result<crate::nhwc::Act, ModelError> {
        let (x, [_, c, h, w]) = pack_input_values(&[frame], &[Some(mask)], &[*intrinsics], &self.config)?;
        net.features(&x, c, h, w)
    }

    /// Per latent cell of `frame` with `mask`, per code: the code head's negated logits, or
    /// without a head the squared distance of the encoder's latent to the code (`[cells *
    /// n_embed]`, cells row-major). Lower is likelier.
    fn code_distances(
        &self,
        frame: &RgbdFrame,
        mask: &[bool],
        intrinsics: &Intrinsics,
    ) -> Result<Vec<f32>, ModelError> {
        let codebook = || self.model.quantize.embedding.weight.val();
        if let Some(net) = self.cpu_net() {
            let feats = self.cpu_features(net, frame, mask, intrinsics)?;
            return match net.neg_logits(&feats) {
                Some(l) => Ok(l.data),
                None => {
                    let z = net.latent(&feats);
                    let rows = Tensor::<2>::from_data(TensorData::new(z.data, [z.h * z.w, z.c]), &self.device);
                    to_host(squared_distances(rows, codebook()))
                }
            };
        }
        let x = pack_input(&[frame], &[Some(mask)], &[*intrinsics], &self.config, &self.device)?;
        match self.model.code_logits(x.clone()) {
            Some(logits) => {
                let [_, kk, zh, zw] = logits.dims();
                to_host(logits.permute([0, 2, 3, 1]).reshape([zh * zw, kk]).neg())
            }
            None => {
                let z = self.model.encode(x);
                let [_, d, zh, zw] = z.dims();
                let rows = z.permute([0, 2, 3, 1]).reshape([zh * zw, d]);
                to_host(squared_distances(rows, codebook()))
            }
        }
    }

    /// Loads from a safetensors file (+ optional config JSON file) on the default device.
    pub fn from_files(weights: &Path, config: Option<&Path>, options: RefinerOptions) -> Result<Self, ModelError> {
        let device = crate::default_device();
        let (model, config) = load_model(weights, config, &device)?;
        Ok(Self::new(model, config, options, device))
    }

    /// Loads from in-memory safetensors bytes (e.g. `include_bytes!`) on the default device.
    pub fn from_bytes(weights: &[u8], config_json: Option<&[u8]>, options: RefinerOptions) -> Result<Self, ModelError> {
        let device = crate::default_device();
        let (model, config) = load_model_bytes(weights, config_json, &device)?;
        Ok(Self::new(model, config, options, device))
    }

    /// The model configuration.
    pub fn config(&self) -> &ModelConfig {
        &self.config
    }

    /// What the last completion chose.
    pub fn trace(&self) -> &SamplingTrace {
        &self.trace
    }

    /// Changes the sampling options and reseeds the RNG.
    pub fn set_options(&mut self, options: RefinerOptions) {
        self.rng = ChaCha8Rng::seed_from_u64(options.seed);
        self.options = options;
    }

    /// Completes one frame: `frame` + `missing` (row-major, true = missing) -> complete frame.
    /// Models with ray channels need the frame's intrinsics: use [`Self::complete_at`].
    pub fn complete(&mut self, frame: &RgbdFrame, missing: &[bool]) -> Result<RgbdFrame, ModelError> {
        self.complete_at(frame, missing, None)
    }

    /// The code selection actually used: for a generative model (`code_tau` set), temperature
    /// `T` means `T * tau` in squared latent distance (in logits for a code head, `tau = 1`),
    /// so `T = 1` samples the trained distribution.
    pub fn effective_sampling(&self) -> Sampling {
        match (self.options.sampling, self.config.code_tau) {
            (Sampling::Temperature { temperature, top_k }, Some(tau)) => {
                Sampling::Temperature { temperature: temperature * tau, top_k }
            }
            (s, _) => s,
        }
    }

    /// Completes one frame seen through `intrinsics` (required by models with ray channels).
    ///
    /// Argmin, or a model without `code_tau`: one pass (encode, select codes, decode). A
    /// generative model sampling a large hole works MaskGIT-style: each pass draws a code for
    /// every open missing cell, commits the most confident share of them (all of them on the
    /// last pass), decodes, and pastes the committed cells' pixels into the guidance as
    /// observed before re-encoding, so later draws see earlier ones. Passes:
    /// `ceil(missing cells / cells_per_pass)`, at most `max_passes` — one for the zig-zag's few
    /// new cells per step.
    pub fn complete_at(
        &mut self,
        frame: &RgbdFrame,
        missing: &[bool],
        intrinsics: Option<&Intrinsics>,
    ) -> Result<RgbdFrame, ModelError> {
        let (w, h) = (frame.width() as usize, frame.height() as usize);
        if missing.len() != w * h {
            return Err(ModelError::shape(
                "the missing mask",
                format!("{} values for a {w}x{h} frame", w * h),
                missing.len(),
            ));
        }
        let intrinsics = match intrinsics {
            Some(k) => *k,
            None if !self.config.ray_channels => Intrinsics::from_fov_x(w as u32, h as u32, 1.0),
            None => {
                return Err(ModelError::MissingPart {
                    part: "the frame's intrinsics",
                    operation: "a model with ray channels",
                })
            }
        };
        let f = self.config.downsample_factor();
        let (pw, ph) = (w.div_ceil(f) * f, h.div_ceil(f) * f);
        let (mut work, mut mask) = pad_frame(frame, missing, pw, ph);
        let (cw, ch) = (pw / f, ph / f);
        let bank_fits = self.bank.as_ref().is_some_and(|b| b.rows == ch && b.cols == cw);
        // with the bank's own pixels, a cell with any missing pixel is quilted: the decoder's
        // drawing of a hole's edge is what the pixels are there to replace
        let quilt_pixels = bank_fits && self.bank_pixels.is_some();
        let threshold = if quilt_pixels { 0.0 } else { self.options.missing_cell_threshold };
        let mut cells = missing_cells(&mask, pw, ph, f, threshold);
        let sampling = self.effective_sampling();
        let sampler = (self.config.code_tau.is_some() || self.config.code_head)
            && matches!(sampling, Sampling::Temperature { .. });
        // the model's own draws: thin bands at the border wait (a bank's search defers its own)
        let wait_cells = match self.options.bands_wait {
            Some(n) if n > 0 && sampler && !bank_fits => crate::bank::thin_border_bands(&cells, ch, cw, n),
            _ => Vec::new(),
        };
        for &c in &wait_cells {
            cells[c] = false;
        }
        let n_missing = cells.iter().filter(|m| **m).count();
        // two-level sampling: the within-class temperature in the same units as the sampling's
        let within = match (sampler, self.options.within_class_temperature) {
            (true, Some(t)) if n_missing > 0 => {
                self.plain_codes()?;
                Some(t * self.config.code_tau.unwrap_or(1.0))
            }
            _ => None,
        };
        // a model without a code head (adapted to a seed) quilts from a seed's pixels too
        if (sampler || quilt_pixels) && n_missing > 0 && bank_fits {
            let mut codes = self.most_likely_codes(&work, &mask, &intrinsics, [ch, cw])?;
            let plain = if self.options.whole_objects { Some(self.plain_codes()?.to_vec()) } else { None };
            self.code_looks()?;
            let (bank, looks) = (self.bank.as_deref(), self.looks.as_deref());
            // quilting pixels as tiles: bands wait as runs, tiles are matched at pixel offsets
            let tiled = quilt_pixels && self.options.quilt_tile > 0;
            // quilting pixels, every hole is filled: a one-cell hole keeps no decoder drawing
            let search = BankSearch {
                min_cells: if quilt_pixels { 1 } else { BankSearch::default().min_cells },
                defer_thinner_than: self.options.bands_wait.unwrap_or(DEFAULT_BANDS_WAIT),
                whole_objects: self.options.whole_objects,
                tile: if tiled { self.options.quilt_tile } else { 0 },
                defer_runs: tiled,
                ..BankSearch::default()
            };
            let (fill, provisional) = match (bank, looks) {
                (Some(bank), Some(looks)) => {
                    // with the bank's pixels, the best matches are ranked again on the band's pixels
                    let block = if tiled { BAND_BLOCK_PX } else { 1 };
                    let distance = self.bank_pixels.as_deref().filter(|_| quilt_pixels).map(|p| {
                        move |frame: usize,
                              shift: [i32; 2],
                              offset: [i32; 2],
                              band: &[usize],
                              pasted: &[Option<Pasted>]| {
                            band_pixel_distance(&work, bank, p, f, (frame, shift, offset), band, pasted, block)
                        }
                    });
                    // with the bank's pixels, a hole takes no cell that has pixels missing (a
                    // real sensor's holes): pasted, they would leave the hole without depth
                    let complete = self.bank_pixels.as_deref().filter(|_| quilt_pixels).map(|p| {
                        let cells = p.complete_cells(bank, f);
                        move |frame: usize, cell: usize| {
                            p.source_index(bank, frame, cell).is_some_and(|(b, [y, x])| cells[b][y * bank.cols + x])
                        }
                    });
                    let hints = FillHints {
                        plain: plain.as_deref(),
                        band_distance: distance.as_ref().map(|d| {
                            d as &(dyn Fn(usize, [i32; 2], [i32; 2], &[usize], &[Option<Pasted>]) -> f32 + Sync)
                        }),
                        // (not with the decoder's colour: it is drawn at the cells, not offset)
                        pixel_offsets: if tiled && !self.bank_colour_from_decoder { (f / 2) as i32 } else { 0 },
                        filled: None,
                        source_usable: complete.as_ref().map(|u| u as &(dyn Fn(usize, usize) -> bool + Sync)),
                    };
                    let fill = bank.fill_with(&mut codes, &cells, looks, &hints, &search, &mut self.rng);
                    // the bands that wait are coloured from the seed too (their depth goes
                    // below), also with the decoder's colour: the code head's codes there are
                    // not the seed's, and their drawing would reach later frames through the
                    // colour warp
                    let provisional = (self.bank_pixels.is_some() && !fill.deferred.is_empty()).then(|| {
                        let mut waiting = vec![false; cells.len()];
                        for &c in &fill.deferred {
                            waiting[c] = true;
                        }
                        let mut scratch = codes.clone();
                        let now = BankSearch { defer_thinner_than: 0, defer_runs: false, ..search };
                        // with tiles, matched on the pixels as well, the cells the fill just
                        // quilted having their sources' pixels; without, by the codes' looks
                        let filled = fill.pasted(cells.len());
                        let hints =
                            if tiled { FillHints { filled: Some(&filled), ..hints } } else { FillHints::default() };
                        bank.fill_with(&mut scratch, &waiting, looks, &hints, &now, &mut self.rng)
                    });
                    (fill, provisional)
                }
                _ => (BankFill::default(), None),
            };
            let colour_from_decoder = quilt_pixels && self.bank_colour_from_decoder;
            let mut out = if quilt_pixels && !colour_from_decoder {
                // nothing is left to the decoder: every cell with a missing pixel is quilted now
                // or waits, and the observed pixels are the guidance's
                frame.clone()
            } else {
                let full = self.decode_codes(&codes, ch, cw)?;
                let mut out = crop_frame(&full, w, h);
                if self.options.keep_observed {
                    keep_observed(&mut out, frame, missing);
                }
                out
            };
            if let (Some(bank), Some(pixels)) = (self.bank.as_deref(), self.bank_pixels.as_deref()) {
                paste_sources(&mut out, missing, &fill, bank, pixels, f, !colour_from_decoder);
                if let Some(provisional) = &provisional {
                    paste_sources(&mut out, missing, provisional, bank, pixels, f, true);
                }
            }
            // deferred cells keep their provisional colour and no depth: nothing is fused there
            drop_depth(&mut out, missing, &fill.deferred, cw, f);
            self.trace = SamplingTrace { codes, missing_cells: cells, bank_draws: fill.draws, ..Default::default() };
            return Ok(out);
        }
        if sampler && n_missing > 0 && self.model.context.is_some() {
            let trace = self.draw_with_context(&work, &mask, &intrinsics, &cells, [ch, cw], within)?;
            let full = self.decode_codes(&trace.codes, ch, cw)?;
            self.trace = SamplingTrace { missing_cells: cells, ..trace };
            let mut out = crop_frame(&full, w, h);
            if self.options.keep_observed {
                keep_observed(&mut out, frame, missing);
            }
            drop_depth(&mut out, missing, &wait_cells, cw, f);
            return Ok(out);
        }
        let passes = if sampler && n_missing > 0 {
            n_missing.div_ceil(self.options.cells_per_pass.max(1)).clamp(1, self.options.max_passes.max(1))
        } else {
            1
        };
        let k = self.config.n_embed;
        let mut committed: Vec<Option<u32>> = vec![None; cells.len()];
        let mut codes = Vec::new();
        let mut passes_log: Vec<Vec<usize>> = Vec::new();
        for pass in 0..passes {
            let dist = self.code_distances(&work, &mask, &intrinsics)?;
            let open: Vec<bool> = cells.iter().zip(&committed).map(|(m, c)| *m && c.is_none()).collect();
            let (drawn, drawn_p) = match (within, sampling) {
                (Some(within), Sampling::Temperature { temperature, .. }) => {
                    let plain = self.plain_codes.as_deref().unwrap_or(&[]);
                    let (d, p) = select_codes_by_class(
                        &dist,
                        cells.len(),
                        k,
                        &open,
                        temperature,
                        within,
                        plain,
                        None,
                        &mut self.rng,
                    );
                    (d, Some(p))
                }
                _ => (select_codes(&dist, cells.len(), k, Some(&open), sampling, &mut self.rng), None),
            };
            codes = drawn.iter().zip(&committed).map(|(d, c)| c.unwrap_or(*d)).collect();
            if pass + 1 == passes {
                passes_log.push((0..cells.len()).filter(|&i| open[i]).collect());
                break;
            }
            let Sampling::Temperature { temperature, .. } = sampling else { break };
            // confidence of each open cell's draw, its probability under the softmax
            let mut conf: Vec<(f32, usize)> = (0..cells.len())
                .filter(|&i| open[i])
                .map(|i| match &drawn_p {
                    Some(p) => (p[i], i),
                    None => (draw_probability(&dist[i * k..(i + 1) * k], drawn[i] as usize, temperature), i),
                })
                .collect();
            let n_commit = conf.len().div_ceil(passes - pass);
            conf.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            let newly: Vec<usize> = conf.iter().take(n_commit).map(|c| c.1).collect();
            passes_log.push(newly.clone());
            for &i in &newly {
                committed[i] = Some(drawn[i]);
            }
            let out = self.decode_codes(&codes, ch, cw)?;
            for &i in &newly {
                let (cy, cx) = (i / cw, i % cw);
                for y in cy * f..(cy + 1) * f {
                    for x in cx * f..(cx + 1) * f {
                        let p = y * pw + x;
                        if mask[p] {
                            work.colour.data[p] = out.colour.data[p];
                            work.depth_m.data[p] = out.depth_m.data[p];
                            mask[p] = false;
                        }
                    }
                }
            }
        }
        let full = self.decode_codes(&codes, ch, cw)?;
        self.trace = SamplingTrace { codes, passes: passes_log, missing_cells: cells, ..Default::default() };
        let mut out = crop_frame(&full, w, h);
        if self.options.keep_observed {
            keep_observed(&mut out, frame, missing);
        }
        drop_depth(&mut out, missing, &wait_cells, cw, f);
        Ok(out)
    }

    /// Decodes `frame` with `hole_codes` (one per latent cell, row-major) in its missing latent
    /// cells and the model's most likely code in the others: what a sampler that drew exactly
    /// these codes would return. Given the true frame's codes
    /// ([`crate::generative::target_codes`]), it is the best any sampler can do with this
    /// codebook and decoder. The frame's sides must be multiples of the downsampling factor.
    pub fn complete_with_codes(
        &mut self,
        frame: &RgbdFrame,
        missing: &[bool],
        intrinsics: &Intrinsics,
        hole_codes: &[u32],
    ) -> Result<RgbdFrame, ModelError> {
        let (w, h, f) = (frame.width() as usize, frame.height() as usize, self.config.downsample_factor());
        if !w.is_multiple_of(f) || !h.is_multiple_of(f) || missing.len() != w * h {
            return Err(ModelError::shape(
                "a frame to decode with given codes",
                format!("sides that are multiples of {f} and a mask of {} values", w * h),
                format!("{w}x{h} and {} values", missing.len()),
            ));
        }
        let (ch, cw) = (h / f, w / f);
        if hole_codes.len() != ch * cw || hole_codes.iter().any(|&c| c as usize >= self.config.n_embed) {
            return Err(ModelError::shape(
                "the hole codes",
                format!("{} codes below {}", ch * cw, self.config.n_embed),
                format!("{} codes", hole_codes.len()),
            ));
        }
        let cells = missing_cells(missing, w, h, f, self.options.missing_cell_threshold);
        let mut codes = self.most_likely_codes(frame, missing, intrinsics, [ch, cw])?;
        for (i, m) in cells.iter().enumerate() {
            if *m {
                codes[i] = hole_codes[i];
            }
        }
        let mut out = self.decode_codes(&codes, ch, cw)?;
        if self.options.keep_observed {
            keep_observed(&mut out, frame, missing);
        }
        Ok(out)
    }

    /// Draws every cell's code with the scene-wide context ([`crate::context`]): the encoder
    /// runs once on the guidance; observed cells take the head's most likely code; the missing
    /// cells are covered by windows of at most `window_cells` per side, each a core of missing
    /// cells with `margin_cells` of context around it, taken in reading order. In a window, the
    /// transformer runs a pass per share of the core's missing cells (`cells_per_pass`, at most
    /// `max_passes`): every open cell draws from head + context logits, and the most
    /// confident draws are committed as revealed tokens for the next pass (all of them on the
    /// last). Returns the codes, the cells committed per pass and the tokens of each pass (the
    /// trace without its missing cells).
    fn draw_with_context(
        &mut self,
        work: &RgbdFrame,
        mask: &[bool],
        intrinsics: &Intrinsics,
        cells: &[bool],
        [ch, cw]: [usize; 2],
        within: Option<f32>,
    ) -> Result<SamplingTrace, ModelError> {
        let hues = match within {
            Some(_) if self.options.hue_coherence > 0.0 => Some(self.code_hues()?.to_vec()),
            _ => None,
        };
        let Some(context) = self.model.context.as_ref() else {
            return Err(ModelError::MissingPart { part: "a context", operation: "context sampling" });
        };
        let Some(head) = self.model.code_head.as_ref() else {
            return Err(ModelError::MissingPart { part: "a code head", operation: "context sampling" });
        };
        let Some(cfg) = self.config.context.clone() else {
            return Err(ModelError::MissingPart { part: "a context in its config", operation: "context sampling" });
        };
        let Sampling::Temperature { temperature, .. } = self.effective_sampling() else {
            return Err(ModelError::MissingPart { part: "a sampling temperature", operation: "context sampling" });
        };
        let sampling = self.effective_sampling();
        let k = self.config.n_embed;
        let z = self.config.z_channels;
        // the encoder's features per cell: host rows with the CPU kernels that take them, else a
        // burn tensor; and the head's logits, negated (lower is likelier)
        enum Features<'a> {
            Host(Vec<f32>, &'a NhwcNet),
            Burn(Box<Tensor<2>>),
        }
        // (the field, not `cpu_net()`: `self.rng` is borrowed mutably while this is held)
        let cpu = self.nhwc.as_ref().filter(|_| self.use_nhwc);
        let (feats, neg_head) = match cpu {
            Some(net) => {
                let feats = self.cpu_features(net, work, mask, intrinsics)?;
                let Some(logits) = net.neg_logits(&feats) else {
                    return Err(ModelError::MissingPart { part: "a code head", operation: "context sampling" });
                };
                (Features::Host(feats.data, net), logits.data)
            }
            None => {
                let x = pack_input(&[work], &[Some(mask)], &[*intrinsics], &self.config, &self.device)?;
                let feats = self.model.features(x);
                let logits = head.forward(feats.clone());
                let neg_head = to_host(logits.permute([0, 2, 3, 1]).reshape([ch * cw, k]).neg())?;
                (Features::Burn(Box::new(feats.permute([0, 2, 3, 1]).reshape([ch * cw, z]))), neg_head)
            }
        };
        // observed cells: the head's most likely code
        let mut codes = select_codes(&neg_head, ch * cw, k, None, Sampling::Argmin, &mut self.rng);
        let mut states: Vec<CellState> =
            cells.iter().map(|&m| if m { CellState::Open } else { CellState::Observed }).collect();
        let codebook = self.model.quantize.embedding.weight.val();
        let mut passes_log = Vec::new();
        let mut tokens = Vec::new();
        for win in context_windows(cells, [ch, cw], cfg.window_cells, cfg.margin_cells) {
            let [wy0, wx0, wh, ww] = win.window;
            let window_cells: Vec<usize> =
                (wy0..wy0 + wh).flat_map(|y| (wx0..wx0 + ww).map(move |x| y * cw + x)).collect();
            let win_feats = match &feats {
                Features::Host(all, net) => Features::Host(
                    window_cells.iter().flat_map(|&i| all[i * z..(i + 1) * z].iter().copied()).collect(),
                    net,
                ),
                Features::Burn(all) => {
                    let idx = Tensor::<1, Int>::from_data(
                        TensorData::new(
                            window_cells.iter().map(|&i| i as i64).collect::<Vec<_>>(),
                            [window_cells.len()],
                        ),
                        &self.device,
                    );
                    Features::Burn(Box::new((**all).clone().select(0, idx)))
                }
            };
            let core_open = |states: &[CellState]| -> Vec<bool> {
                window_cells.iter().map(|&i| states[i] == CellState::Open && win.contains(i / cw, i % cw)).collect()
            };
            let n_open = core_open(&states).iter().filter(|o| **o).count();
            if n_open == 0 {
                continue;
            }
            let passes = n_open.div_ceil(self.options.cells_per_pass.max(1)).clamp(1, self.options.max_passes.max(1));
            for pass in 0..passes {
                let open = core_open(&states);
                let win_states: Vec<CellState> = window_cells.iter().map(|&i| states[i]).collect();
                let residual = match &win_feats {
                    Features::Host(f, net) => match net.context_residual(f, &win_states, [wh, ww]) {
                        Some(r) => r?,
                        None => {
                            return Err(ModelError::MissingPart {
                                part: "a context in the CPU kernels",
                                operation: "context sampling",
                            })
                        }
                    },
                    Features::Burn(f) => {
                        let input = ContextInput::new((**f).clone(), &win_states, &codebook, [1, wh, ww]);
                        to_host(context.forward(input))?
                    }
                };
                let mut dist: Vec<f32> = window_cells
                    .iter()
                    .enumerate()
                    .flat_map(|(j, &i)| {
                        let (h, r) = (&neg_head[i * k..(i + 1) * k], &residual[j * k..(j + 1) * k]);
                        h.iter().zip(r).map(|(a, b)| a - b)
                    })
                    .collect();
                let n = window_cells.len();
                // the class coherence shifts the class odds two-level sampling draws from
                if let Some(plain) = self.plain_codes.as_deref().filter(|_| within.is_some()) {
                    let strength = self.options.class_coherence;
                    class_bias(&mut dist, &window_cells, &open, &states, &codes, plain, [ch, cw], strength);
                }
                let bias = hues
                    .as_deref()
                    .map(|h| hue_bias(&window_cells, &open, &states, &codes, h, [ch, cw], self.options.hue_coherence));
                let (drawn, drawn_p) = match within {
                    Some(within) => {
                        let plain = self.plain_codes.as_deref().unwrap_or(&[]);
                        let (d, p) = select_codes_by_class(
                            &dist,
                            n,
                            k,
                            &open,
                            temperature,
                            within,
                            plain,
                            bias.as_deref(),
                            &mut self.rng,
                        );
                        (d, Some(p))
                    }
                    None => (select_codes(&dist, n, k, Some(&open), sampling, &mut self.rng), None),
                };
                let mut conf: Vec<(f32, usize)> = (0..n)
                    .filter(|&j| open[j])
                    .map(|j| match &drawn_p {
                        Some(p) => (p[j], j),
                        None => (draw_probability(&dist[j * k..(j + 1) * k], drawn[j] as usize, temperature), j),
                    })
                    .collect();
                let n_commit = if pass + 1 == passes { conf.len() } else { conf.len().div_ceil(passes - pass) };
                conf.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
                let mut newly = Vec::with_capacity(n_commit);
                for &(_, j) in conf.iter().take(n_commit) {
                    let i = window_cells[j];
                    codes[i] = drawn[j];
                    states[i] = CellState::Revealed(drawn[j]);
                    newly.push(i);
                }
                passes_log.push(newly);
                tokens.push(n);
            }
        }
        Ok(SamplingTrace {
            codes,
            passes: passes_log,
            missing_cells: Vec::new(),
            context_tokens: tokens,
            bank_draws: Vec::new(),
        })
    }

    /// Completes holes from `bank` ([`crate::bank`]) instead of sampling codes, when the bank's
    /// grid is the frame's (other sizes keep the learned sampler). The bank must index this
    /// model's codebook.
    pub fn set_bank(&mut self, bank: Option<std::sync::Arc<CodeBank>>) -> Result<(), ModelError> {
        if let Some(b) = &bank {
            if b.n_embed != self.config.n_embed {
                return Err(ModelError::shape("the code bank's codebook", self.config.n_embed, b.n_embed));
            }
            let ours = self.codebook_crc32()?;
            if b.codebook_crc32 != ours {
                return Err(ModelError::config(
                    "code bank",
                    format!(
                        "built with another model's codebook (CRC {:08x}, this model's {ours:08x}); \
                         build one for this model with `sgam train bank --model ...`",
                        b.codebook_crc32
                    ),
                ));
            }
        }
        self.bank = bank;
        Ok(())
    }

    /// With the bank's pixels ([`Self::set_bank_pixels`]): `true` keeps the decoder's colour in
    /// the holes and takes only the pixels' depth (for a decoder adapted to the seed, which draws
    /// a quilted piece continuing what surrounds it); `false` (the default) pastes both.
    pub fn set_bank_colour_from_decoder(&mut self, on: bool) {
        self.bank_colour_from_decoder = on;
    }

    /// The pixels behind the bank's codes ([`BankPixels`]; the bank's frames must be the run's
    /// size): a hole the bank fills takes them instead of the decoder's output. `None` decodes
    /// the codes.
    pub fn set_bank_pixels(&mut self, pixels: Option<std::sync::Arc<BankPixels>>) {
        self.bank_pixels = pixels;
    }

    /// CRC-32 of the codebook (its f32 values, little-endian): what a [`CodeBank`] is tied to.
    pub fn codebook_crc32(&self) -> Result<u32, ModelError> {
        let w: Vec<f32> = to_host(self.model.quantize.embedding.weight.val())?;
        let bytes: Vec<u8> = w.iter().flat_map(|v| v.to_le_bytes()).collect();
        Ok(crc32fast::hash(&bytes))
    }

    /// The code bank in use, if any.
    pub fn bank(&self) -> Option<&CodeBank> {
        self.bank.as_deref()
    }

    /// The model's most likely code of every latent cell of a complete frame (the encoder's
    /// argmin, or the code head's argmax): what a bank stores. Sides must be multiples of the
    /// downsampling factor.
    pub fn frame_codes(&mut self, frame: &RgbdFrame, intrinsics: &Intrinsics) -> Result<Vec<u32>, ModelError> {
        let mask = vec![false; frame.width() as usize * frame.height() as usize];
        self.frame_codes_missing(frame, &mask, intrinsics)
    }

    /// [`Self::frame_codes`] of a frame with pixels the model is told are missing (a real
    /// seed's holes and sky): their cells take the model's completion.
    pub fn frame_codes_missing(
        &mut self,
        frame: &RgbdFrame,
        missing: &[bool],
        intrinsics: &Intrinsics,
    ) -> Result<Vec<u32>, ModelError> {
        let (w, h, f) = (frame.width() as usize, frame.height() as usize, self.config.downsample_factor());
        if !w.is_multiple_of(f) || !h.is_multiple_of(f) || missing.len() != w * h {
            return Err(ModelError::shape(
                "a frame to encode",
                format!("sides that are multiples of {f} and a mask of {} values", w * h),
                format!("{w}x{h} and {} values", missing.len()),
            ));
        }
        self.most_likely_codes(frame, missing, intrinsics, [h / f, w / f])
    }

    /// One encoder pass over a (padded) frame: the most likely code of every cell.
    fn most_likely_codes(
        &mut self,
        frame: &RgbdFrame,
        mask: &[bool],
        intrinsics: &Intrinsics,
        [ch, cw]: [usize; 2],
    ) -> Result<Vec<u32>, ModelError> {
        let k = self.config.n_embed;
        let dist = self.code_distances(frame, mask, intrinsics)?;
        Ok(select_codes(&dist, ch * cw, k, None, Sampling::Argmin, &mut self.rng))
    }

    /// Per code, how it looks: mean colour (sRGB, `[0, 1]`) and mean normalised disparity
    /// (`[0, 1]`, near = 1) of the centre of its decoded patch ([`Self::code_patch_means`],
    /// computed once). The bank matches holes with it.
    pub fn code_looks(&mut self) -> Result<&[[f32; 4]], ModelError> {
        if self.looks.is_none() {
            let depth = self.config.depth;
            self.looks = Some(self.code_patch_means(|frame, i| {
                let c = frame.colour.data[i];
                [c[0], c[1], c[2], normalised_disparity(frame.depth_m.data[i], &depth)]
            })?);
        }
        Ok(self.looks.as_deref().unwrap_or(&[]))
    }

    /// Which codes are plain (grey: CLEVR's ground) rather than coloured, for two-level
    /// sampling: a code is plain when the mean HSV saturation of the centre of its decoded patch
    /// ([`Self::code_patch_means`]) is below [`PLAIN_CODE_SATURATION`]. Computed once per
    /// refiner.
    pub fn plain_codes(&mut self) -> Result<&[bool], ModelError> {
        if self.plain_codes.is_none() {
            let means = self.code_patch_means(|frame, i| [saturation(frame.colour.data[i])])?;
            self.plain_codes = Some(means.iter().map(|[m]| *m < PLAIN_CODE_SATURATION).collect());
        }
        Ok(self.plain_codes.as_deref().unwrap_or(&[]))
    }

    /// Per code, the unit direction of its patch's mean chroma (`r - (g + b) / 2`,
    /// `sqrt(3) / 2 (g - b)`: the angle is the hue), zero for the plain codes
    /// ([`Self::plain_codes`]) and for a patch whose mean chroma is under [`MIN_HUE_CHROMA`].
    pub fn code_hues(&mut self) -> Result<&[[f32; 2]], ModelError> {
        if self.code_hues.is_none() {
            let plain = self.plain_codes()?.to_vec();
            let means = self.code_patch_means(|frame, i| {
                let [r, g, b] = frame.colour.data[i];
                [r - 0.5 * (g + b), 0.866_025_4 * (g - b)]
            })?;
            let hues = means
                .iter()
                .zip(&plain)
                .map(|(&[a, b], &plain)| {
                    let norm = (a * a + b * b).sqrt();
                    // a patch whose colours cancel out has no hue to keep
                    if plain || norm < MIN_HUE_CHROMA {
                        [0.0, 0.0]
                    } else {
                        [a / norm, b / norm]
                    }
                })
                .collect();
            self.code_hues = Some(hues);
        }
        Ok(self.code_hues.as_deref().unwrap_or(&[]))
    }

    /// Per code, the mean of `pixel` (given the decoded frame and a pixel index) over the centre
    /// 2x2 cells of the code decoded alone as a uniform 4x4-cell patch (64 codes per decoder
    /// call).
    fn code_patch_means<const N: usize>(
        &self,
        pixel: impl Fn(&RgbdFrame, usize) -> [f32; N],
    ) -> Result<Vec<[f32; N]>, ModelError> {
        let k = self.config.n_embed;
        let f = self.config.downsample_factor();
        let (g, batch) = (4usize, 64usize);
        let mut means = Vec::with_capacity(k);
        for start in (0..k).step_by(batch) {
            let codes: Vec<u32> = (start..(start + batch).min(k)).map(|c| c as u32).collect();
            let b = codes.len();
            let idx: Vec<u32> = codes.iter().flat_map(|&c| std::iter::repeat_n(c, g * g)).collect();
            let rows = self.model.quantize.lookup(&idx, &self.device);
            let [_, d] = rows.dims();
            let z_q = rows.reshape([b, g, g, d]).permute([0, 3, 1, 2]);
            for frame in unpack(self.model.decode(z_q), &self.config.depth)? {
                let w = frame.width() as usize;
                let (mut sum, mut n) = ([0.0f32; N], 0.0f32);
                for y in f..(g - 1) * f {
                    for x in f..(g - 1) * f {
                        for (acc, v) in sum.iter_mut().zip(pixel(&frame, y * w + x)) {
                            *acc += v;
                        }
                        n += 1.0;
                    }
                }
                means.push(sum.map(|v| v / n.max(1.0)));
            }
        }
        Ok(means)
    }

    /// Decodes one code per latent cell (row-major `[h, w]`) into a frame.
    fn decode_codes(&self, codes: &[u32], h: usize, w: usize) -> Result<RgbdFrame, ModelError> {
        if let Some(net) = self.cpu_net() {
            let f = self.config.downsample_factor();
            let planes = net.decode_codes(codes, h, w)?;
            return unpack_values(&planes, [1, 4, h * f, w * f], &self.config.depth)?
                .pop()
                .ok_or(ModelError::EmptyBatch("decoding codes"));
        }
        let rows = self.model.quantize.lookup(codes, &self.device);
        let [_, d] = rows.dims();
        let z_q = rows.reshape([1, h, w, d]).permute([0, 3, 1, 2]);
        unpack(self.model.decode(z_q), &self.config.depth)?.pop().ok_or(ModelError::EmptyBatch("decoding codes"))
    }
}

/// [`RefinerOptions::class_coherence`] on a window's negated logits `dist` (row-major
/// `[window_cells.len(), k]`, lower is likelier): every coloured code of an open cell is made
/// `strength * (coloured - plain) / decided` likelier, counting its decided 4-neighbours
/// (`codes` holds the observed cells' most likely codes) by the class of their code. A
/// shift of the whole class: the odds within it are unchanged. No decided neighbour, or
/// `strength` 0: no change.
#[allow(clippy::too_many_arguments)]
pub(crate) fn class_bias(
    dist: &mut [f32],
    window_cells: &[usize],
    open: &[bool],
    states: &[CellState],
    codes: &[u32],
    plain: &[bool],
    [ch, cw]: [usize; 2],
    strength: f32,
) {
    let k = plain.len();
    if strength == 0.0 || k == 0 || dist.len() != window_cells.len() * k {
        return;
    }
    for (j, &i) in window_cells.iter().enumerate() {
        if !open.get(j).copied().unwrap_or(false) {
            continue;
        }
        let (y, x) = (i / cw, i % cw);
        let neighbours = [
            (y > 0).then(|| i - cw),
            (y + 1 < ch).then(|| i + cw),
            (x > 0).then(|| i - 1),
            (x + 1 < cw).then(|| i + 1),
        ];
        let (mut coloured, mut flat) = (0i32, 0i32);
        for n in neighbours.into_iter().flatten() {
            if states.get(n).is_none_or(|s| *s == CellState::Open) {
                continue;
            }
            match codes.get(n).and_then(|&c| plain.get(c as usize)) {
                Some(true) => flat += 1,
                Some(false) => coloured += 1,
                None => {}
            }
        }
        if coloured + flat == 0 {
            continue;
        }
        let shift = strength * (coloured - flat) as f32 / (coloured + flat) as f32;
        for (d, _) in dist[j * k..(j + 1) * k].iter_mut().zip(plain).filter(|(_, p)| !**p) {
            *d -= shift;
        }
    }
}

/// The within-class bias of [`RefinerOptions::hue_coherence`] for a window's cells (row-major
/// `[window_cells.len(), k]`): an open cell whose 8 neighbours hold coloured codes (observed or
/// revealed; `codes` holds the observed cells' most likely codes) pays `strength * (1 - cos)
/// / 2` for each coloured code by the angle between its hue and the neighbours' summed hue;
/// cells with less than half a coloured neighbour's worth of hue, plain codes and closed
/// cells pay nothing.
pub(crate) fn hue_bias(
    window_cells: &[usize],
    open: &[bool],
    states: &[CellState],
    codes: &[u32],
    hues: &[[f32; 2]],
    [ch, cw]: [usize; 2],
    strength: f32,
) -> Vec<f32> {
    let k = hues.len();
    let mut bias = vec![0.0f32; window_cells.len() * k];
    for (j, &i) in window_cells.iter().enumerate() {
        if !open.get(j).copied().unwrap_or(false) {
            continue;
        }
        let (y, x) = ((i / cw) as isize, (i % cw) as isize);
        let mut sum = [0.0f32; 2];
        for (dy, dx) in [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)] {
            let (ny, nx) = (y + dy, x + dx);
            if ny < 0 || nx < 0 || ny >= ch as isize || nx >= cw as isize {
                continue;
            }
            let n = ny as usize * cw + nx as usize;
            let code = match states.get(n) {
                Some(CellState::Revealed(c)) => *c,
                Some(CellState::Observed) => codes.get(n).copied().unwrap_or(0),
                _ => continue,
            };
            if let Some(h) = hues.get(code as usize) {
                sum[0] += h[0];
                sum[1] += h[1];
            }
        }
        let norm = (sum[0] * sum[0] + sum[1] * sum[1]).sqrt();
        if norm < 0.5 {
            continue;
        }
        let u = [sum[0] / norm, sum[1] / norm];
        for (b, h) in bias[j * k..(j + 1) * k].iter_mut().zip(hues) {
            if h[0] != 0.0 || h[1] != 0.0 {
                *b = strength * (1.0 - (h[0] * u[0] + h[1] * u[1])) * 0.5;
            }
        }
    }
    bias
}

/// One window of context sampling: the cells it draws (`core`, row-major `[y0, x0, h, w]` in
/// latent cells) and the cells it sees (`window`, the core with its margin, inside the grid).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ContextWindow {
    /// Cells drawn: `[y0, x0, h, w]`.
    pub core: [usize; 4],
    /// Cells seen: `[y0, x0, h, w]`.
    pub window: [usize; 4],
}

impl ContextWindow {
    fn contains(&self, y: usize, x: usize) -> bool {
        let [y0, x0, h, w] = self.core;
        (y0..y0 + h).contains(&y) && (x0..x0 + w).contains(&x)
    }
}

/// Windows covering the missing cells of a `[rows, cols]` grid: the missing cells' bounding box
/// is cut into cores of at most `window - 2 margin` cells per side, in reading order, and each
/// core gets `margin` cells of context on every side, shifted inward at the grid's border so a
/// window keeps `window` cells per side where the grid allows. Cores without a missing cell are
/// left out.
pub fn context_windows(missing: &[bool], [rows, cols]: [usize; 2], window: usize, margin: usize) -> Vec<ContextWindow> {
    let found = (0..rows * cols).filter(|&i| missing.get(i).copied().unwrap_or(false));
    let (mut y0, mut x0, mut y1, mut x1) = (usize::MAX, usize::MAX, 0, 0);
    for i in found {
        let (y, x) = (i / cols, i % cols);
        (y0, x0, y1, x1) = (y0.min(y), x0.min(x), y1.max(y + 1), x1.max(x + 1));
    }
    if y0 == usize::MAX {
        return Vec::new();
    }
    let core = window.saturating_sub(2 * margin).max(1);
    let place = |start: usize, len: usize, size: usize| -> (usize, usize) {
        // a window of `window` cells (or the whole axis) around [start, start + len)
        let side = window.min(size).max(len.min(size));
        let lo = start.saturating_sub(margin).min(size - side);
        (lo, side)
    };
    let mut out = Vec::new();
    for cy in (y0..y1).step_by(core) {
        for cx in (x0..x1).step_by(core) {
            let (ch, cw) = (core.min(y1 - cy), core.min(x1 - cx));
            let any = (cy..cy + ch).any(|y| (cx..cx + cw).any(|x| missing[y * cols + x]));
            if !any {
                continue;
            }
            let (wy, wh) = place(cy, ch, rows);
            let (wx, ww) = place(cx, cw, cols);
            out.push(ContextWindow { core: [cy, cx, ch, cw], window: [wy, wx, wh, ww] });
        }
    }
    out
}

/// Saturation below which a decoded code counts as plain (see [`VqRefiner::plain_codes`]). On
/// the bundled model the decoded saturations of its 1,024 codes split into 557 below 0.03
/// (all of them codes the frozen encoder gives to grey cells of real frames) and a spread of
/// coloured ones above (docs/MODEL.md, session 12).
pub const PLAIN_CODE_SATURATION: f32 = 0.03;
/// `s` of [`DepthCoding`](crate::DepthCoding) for planar depth `z` (metres), clamped to `[0, 1]`;
/// 0 where the depth is missing.
fn normalised_disparity(z: f32, coding: &crate::DepthCoding) -> f32 {
    if !(z > 0.0 && z.is_finite()) {
        return 0.0;
    }
    let (a, b) = (1.0 / coding.near_m, 1.0 / coding.far_m);
    ((1.0 / (z + coding.offset_m) - b) / (a - b)).clamp(0.0, 1.0)
}

/// HSV saturation `(max - min) / max` of a linear RGB colour in [0, 1] (0 for black).
fn saturation(c: [f32; 3]) -> f32 {
    let hi = c[0].max(c[1]).max(c[2]);
    let lo = c[0].min(c[1]).min(c[2]);
    if hi <= 1e-6 {
        0.0
    } else {
        (hi - lo) / hi
    }
}

/// Probability of code `j` under `softmax(-row / temperature)` (row = squared distances).
fn draw_probability(row: &[f32], j: usize, temperature: f32) -> f32 {
    let dmin = row.iter().copied().fold(f32::INFINITY, f32::min);
    let t = temperature.max(1e-12) as f64;
    let total: f64 = row.iter().map(|&d| (-((d - dmin) as f64) / t).exp()).sum();
    ((-((row[j] - dmin) as f64) / t).exp() / total.max(1e-300)) as f32
}

/// Copies the observed pixels (`!missing`) of `guidance` into `out` (same size).
fn keep_observed(out: &mut RgbdFrame, guidance: &RgbdFrame, missing: &[bool]) {
    let colour = out.colour.data.iter_mut().zip(&guidance.colour.data);
    let depth = out.depth_m.data.iter_mut().zip(&guidance.depth_m.data);
    for ((c, d), _) in colour.zip(depth).zip(missing).filter(|(_, m)| !**m) {
        *c.0 = *c.1;
        *d.0 = *d.1;
    }
}

fn pad_frame(frame: &RgbdFrame, missing: &[bool], pw: usize, ph: usize) -> (RgbdFrame, Vec<bool>) {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    if (pw, ph) == (w, h) {
        return (frame.clone(), missing.to_vec());
    }
    let mut out = RgbdFrame::empty(pw as u32, ph as u32);
    let mut mask = vec![true; pw * ph];
    for y in 0..h {
        for x in 0..w {
            out.colour.data[y * pw + x] = frame.colour.data[y * w + x];
            out.depth_m.data[y * pw + x] = frame.depth_m.data[y * w + x];
            mask[y * pw + x] = missing[y * w + x];
        }
    }
    (out, mask)
}

fn crop_frame(frame: &RgbdFrame, w: usize, h: usize) -> RgbdFrame {
    let pw = frame.width() as usize;
    if pw == w && frame.height() as usize == h {
        return frame.clone();
    }
    let colour = (0..h).flat_map(|y| (0..w).map(move |x| (y, x))).map(|(y, x)| frame.colour.data[y * pw + x]).collect();
    let depth = (0..h).flat_map(|y| (0..w).map(move |x| (y, x))).map(|(y, x)| frame.depth_m.data[y * pw + x]).collect();
    RgbdFrame {
        colour: Image { width: w as u32, height: h as u32, data: colour },
        depth_m: Image { width: w as u32, height: h as u32, data: depth },
    }
}

impl Refiner for VqRefiner {
    type Error = ModelError;

    /// Sampling draws are seeded per frame from `options.seed` (multiplied by an odd constant) and
    /// `guidance.seed`, so a frame's
    /// result does not depend on what was refined before it (resumed runs equal uninterrupted ones).
    fn refine(&mut self, guidance: &Guidance) -> Result<RgbdFrame, ModelError> {
        // the generator's per-step seed already mixes in the run seed, which is usually this
        // options' seed too: a plain XOR cancelled them (every --seed grew the same world)
        self.rng = ChaCha8Rng::seed_from_u64(self.options.seed.wrapping_mul(0xD1B5_4A32_D192_ED03) ^ guidance.seed);
        self.complete_at(&guidance.frame, &guidance.missing, Some(&guidance.camera.intrinsics))
    }
}

/// With tiles ([`RefinerOptions::quilt_tile`]), a band is compared with a candidate by the mean
/// colours of `BAND_BLOCK_PX x BAND_BLOCK_PX` blocks, not pixel by pixel: a texture continued a
/// pixel or two out of step (the band was warped and resampled since it was pasted) then costs
/// little, where pixel by pixel a smooth candidate (a road, a lawn) beat it, and spread
/// (docs/MODEL.md, session 22).
const BAND_BLOCK_PX: usize = 4;

/// The pixel of base frame `base` at `[y, x]` of cell-aligned coordinates moved by `offset`
/// pixels, clamped to the frame: its index.
fn offset_index(base: &RgbdFrame, y: usize, x: usize, offset: [i32; 2]) -> usize {
    let (bw, bh) = (base.width() as i64, base.height() as i64);
    let yy = (y as i64 + offset[0] as i64).clamp(0, bh - 1);
    let xx = (x as i64 + offset[1] as i64).clamp(0, bw - 1);
    (yy * bw + xx) as usize
}

/// Mean colour distance (L1 over R, G, B, divided by 3) between the pixels of the border band
/// cells `band` of `frame` (padded to the grid) and the pixels behind bank frame `bank_frame`
/// shifted by `shift` cells and `offset` pixels, `f x f` per cell, compared as the mean colours
/// of `block x block` blocks (1: pixel by pixel); a cell the shift moves out of the bank frame
/// counts 1. A band cell filled earlier in the same completion (`pasted[j]`)
/// has the pixels of its source, which `frame` does not hold yet.
fn band_pixel_distance(
    frame: &RgbdFrame,
    bank: &CodeBank,
    pixels: &BankPixels,
    f: usize,
    (bank_frame, shift, offset): (usize, [i32; 2], [i32; 2]),
    band: &[usize],
    pasted: &[Option<Pasted>],
    block: usize,
) -> f32 {
    let w = frame.width() as usize;
    let blk = block.clamp(1, f);
    let (mut sum, mut n) = (0.0f32, 0usize);
    for (j, &cell) in band.iter().enumerate() {
        let (y, x) = ((cell / bank.cols) as i32 + shift[0], (cell % bank.cols) as i32 + shift[1]);
        if y < 0 || x < 0 || y >= bank.rows as i32 || x >= bank.cols as i32 {
            sum += (f * f) as f32;
            n += f * f;
            continue;
        }
        let Some((base, [sy, sx])) = pixels.source(bank, bank_frame, y as usize * bank.cols + x as usize) else {
            continue;
        };
        // the band cell's own pixels: the frame's, or those of what was pasted there
        let own = match pasted.get(j).copied().flatten() {
            Some(p) => match pixels.source(bank, p.frame, p.cell) {
                Some((b, at)) => Some((b, at, p.offset_px)),
                None => continue,
            },
            None => None,
        };
        let (cy, cx) = (cell / bank.cols, cell % bank.cols);
        for by in (0..f).step_by(blk) {
            for bx in (0..f).step_by(blk) {
                let (mut mp, mut mq, mut k) = ([0.0f32; 3], [0.0f32; 3], 0usize);
                for dy in by..(by + blk).min(f) {
                    for dx in bx..(bx + blk).min(f) {
                        let q = &base.colour.data[offset_index(base, sy * f + dy, sx * f + dx, offset)];
                        let p = match own {
                            Some((b, [oy, ox], o)) => &b.colour.data[offset_index(b, oy * f + dy, ox * f + dx, o)],
                            None => match frame.colour.data.get((cy * f + dy) * w + cx * f + dx) {
                                Some(p) => p,
                                None => continue,
                            },
                        };
                        for c in 0..3 {
                            mp[c] += p[c];
                            mq[c] += q[c];
                        }
                        k += 1;
                    }
                }
                if k > 0 {
                    let d: f32 = (0..3).map(|c| (mp[c] - mq[c]).abs()).sum::<f32>() / (3 * k) as f32;
                    sum += d * k as f32;
                    n += k;
                }
            }
        }
    }
    if n == 0 {
        1.0
    } else {
        sum / n as f32
    }
}

/// Takes the depth off the missing pixels of latent `cells` (`cols` per row, `f` pixels a side)
/// of `out`: a hole that waits keeps a provisional colour, and nothing is fused there.
fn drop_depth(out: &mut RgbdFrame, missing: &[bool], cells: &[usize], cols: usize, f: usize) {
    let (w, h) = (out.width() as usize, out.height() as usize);
    for &c in cells {
        let (cy, cx) = (c / cols, c % cols);
        for y in cy * f..((cy + 1) * f).min(h) {
            for x in cx * f..((cx + 1) * f).min(w) {
                if missing[y * w + x] {
                    out.depth_m.data[y * w + x] = 0.0;
                }
            }
        }
    }
}

/// Copies into the missing pixels of `out` the pixels behind each quilted cell's source
/// (`[cell, bank frame, bank cell]`, [`BankFill::sources`], draw after draw as `draws` count
/// them, each moved by its draw's pixel offset): an `f x f` block of colour and depth from the
/// bank's base frame. Blocks past `out`'s edges (padding) are cut. A hole's depths (all its
/// tiles') are scaled to its surroundings: by the median ratio of the observed depth around it
/// to the source's depth at the same places (the cells next to the hole's and their sources'
/// neighbours), so a piece of the seed taken from nearer or farther sits at the depth of the
/// surface it continues. Without `colour` only the depth is pasted.
fn paste_sources(
    out: &mut RgbdFrame,
    missing: &[bool],
    fill: &BankFill,
    bank: &CodeBank,
    pixels: &BankPixels,
    f: usize,
    colour: bool,
) {
    let (w, h) = (out.width() as usize, out.height() as usize);
    let (rows, cols) = (bank.rows as i64, bank.cols as i64);
    let valid = sgam_core::is_valid_depth;
    // every filled cell with its draw's pixel offset and hole: `([cell, bank frame, bank cell], offset, hole)`
    let cells: Vec<([usize; 3], [i32; 2], usize)> =
        fill.filled_cells().map(|(s, d)| (s, d.offset_px, d.hole)).collect();
    for hole in cells.chunk_by(|a, b| a.2 == b.2) {
        let in_hole: std::collections::HashSet<usize> = hole.iter().map(|s| s.0[0]).collect();
        // the depth ratios around the hole
        let mut ratios = Vec::new();
        for &([cell, frame, source], offset, _) in hole {
            let (cy, cx) = ((cell / bank.cols) as i64, (cell % bank.cols) as i64);
            let (sy, sx) = ((source / bank.cols) as i64, (source % bank.cols) as i64);
            for (dy, dx) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                let (ny, nx, my, mx) = (cy + dy, cx + dx, sy + dy, sx + dx);
                if ny < 0 || nx < 0 || ny >= rows || nx >= cols || my < 0 || mx < 0 || my >= rows || mx >= cols {
                    continue;
                }
                if in_hole.contains(&((ny * cols + nx) as usize)) {
                    continue;
                }
                let Some((base, [by, bx])) = pixels.source(bank, frame, (my * cols + mx) as usize) else { continue };
                for py in 0..f {
                    for px in 0..f {
                        let (y, x) = (ny as usize * f + py, nx as usize * f + px);
                        if y >= h || x >= w || missing[y * w + x] {
                            continue;
                        }
                        let t = out.depth_m.data[y * w + x];
                        let s = base.depth_m.data[offset_index(base, by * f + py, bx * f + px, offset)];
                        if valid(t) && valid(s) {
                            ratios.push(t / s);
                        }
                    }
                }
            }
        }
        let scale = if ratios.len() >= 8 {
            let mid = ratios.len() / 2;
            ratios.select_nth_unstable_by(mid, f32::total_cmp);
            ratios[mid].clamp(0.25, 4.0)
        } else {
            1.0
        };
        for &([cell, frame, source], offset, _) in hole {
            let Some((base, [sy, sx])) = pixels.source(bank, frame, source) else { continue };
            let (cy, cx) = (cell / bank.cols, cell % bank.cols);
            for dy in 0..f {
                for dx in 0..f {
                    let (y, x) = (cy * f + dy, cx * f + dx);
                    if y >= h || x >= w || !missing[y * w + x] {
                        continue;
                    }
                    // a pixel the offset reaches outside the source cell may lack depth (the
                    // seed's sky, a sensor's hole): the cell's own pixel then, which has it
                    let mut b = offset_index(base, sy * f + dy, sx * f + dx, offset);
                    if !valid(base.depth_m.data[b]) {
                        b = offset_index(base, sy * f + dy, sx * f + dx, [0, 0]);
                    }
                    if colour {
                        out.colour.data[y * w + x] = base.colour.data[b];
                    }
                    out.depth_m.data[y * w + x] = base.depth_m.data[b] * scale;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3 x 3 code grid's cell states, window and open cells: the top row observed, the middle
    /// row open, the bottom-left cell revealed as code `revealed` and the rest of it open.
    fn three_by_three(revealed: u32) -> (Vec<CellState>, Vec<usize>, Vec<bool>) {
        let mut states = vec![CellState::Observed; 3];
        states.extend([CellState::Open; 3]);
        states.extend([CellState::Revealed(revealed), CellState::Open, CellState::Open]);
        let open = states.iter().map(|s| *s == CellState::Open).collect();
        (states, (0..9).collect(), open)
    }

    #[test]
    fn a_cell_next_to_red_cells_pays_for_blue_codes_and_not_for_red_ones() {
        // codes: 0 plain, 1 red, 2 blue (opposite chroma), 3 a red turned a right angle
        let hues = [[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]];
        let (ch, cw) = (3usize, 3usize);
        // row 0 observed red, row 1 open, row 2: revealed blue on the left, open elsewhere
        let (states, window, open) = three_by_three(2);
        let codes = vec![1, 1, 1, 0, 0, 0, 0, 0, 0];
        let bias = hue_bias(&window, &open, &states, &codes, &hues, [ch, cw], 4.0);
        let at = |cell: usize, code: usize| bias[cell * 4 + code];
        // the middle right cell (5) sees two red observed cells and no blue one
        assert_eq!((at(5, 0), at(5, 1)), (0.0, 0.0), "plain and same-hue codes are free");
        assert!((at(5, 2) - 4.0).abs() < 1e-5, "the opposite hue pays the whole strength");
        assert!((at(5, 3) - 2.0).abs() < 1e-5, "a right angle pays half");
        // cell 8 (bottom right) sees only open cells: no hue, no bias
        assert!(bias[8 * 4..9 * 4].iter().all(|b| *b == 0.0));
        // closed cells carry none
        assert!(bias[..3 * 4].iter().all(|b| *b == 0.0));
        // cell 3 sees two red cells above and the revealed blue one below: red wins the sum
        assert!((at(3, 2) - 4.0).abs() < 1e-5 && at(3, 1) == 0.0);
        // cell 4 sees three red and one blue: the same direction
        assert!((at(4, 2) - 4.0).abs() < 1e-5);
    }

    #[test]
    fn a_cell_between_coloured_cells_leans_coloured_and_one_on_the_ground_plain() {
        // codes: 0 and 1 plain, 2 and 3 coloured; a 3 x 3 grid, every cell open but the
        // top row (observed: coloured, coloured, plain) and the revealed bottom-left (plain)
        let plain = [true, true, false, false];
        let (ch, cw, k) = (3usize, 3usize, 4usize);
        let (states, window, open) = three_by_three(0);
        let codes = vec![2, 3, 0, 0, 0, 0, 0, 0, 0];
        let before: Vec<f32> = (0..9 * k).map(|i| (i % 5) as f32).collect();
        let mut dist = before.clone();
        class_bias(&mut dist, &window, &open, &states, &codes, &plain, [ch, cw], 2.0);
        let moved = |cell: usize, code: usize| dist[cell * k + code] - before[cell * k + code];
        // cell 4 (centre): one decided neighbour above, coloured: coloured codes 2 likelier
        assert_eq!((moved(4, 0), moved(4, 1), moved(4, 2), moved(4, 3)), (0.0, 0.0, -2.0, -2.0));
        // cell 3 (middle left): coloured above, plain below: no lean
        assert_eq!(moved(3, 2), 0.0);
        // cell 5 (middle right): plain above: coloured codes 2 less likely
        assert_eq!((moved(5, 2), moved(5, 3), moved(5, 0)), (2.0, 2.0, 0.0));
        // cell 8 sees only open cells; decided cells are never moved
        assert!((0..k).all(|c| moved(8, c) == 0.0 && moved(0, c) == 0.0 && moved(6, c) == 0.0));
        // strength 0: nothing moves
        let mut same = before.clone();
        class_bias(&mut same, &window, &open, &states, &codes, &plain, [ch, cw], 0.0);
        assert_eq!(same, before);
    }

    /// A `side x side` frame whose every pixel has its own colour, and depth `depth`.
    fn textured(side: u32, depth: f32) -> RgbdFrame {
        let n = (side * side) as usize;
        let colour =
            (0..n).map(|i| [(i % 7) as f32 / 7.0, (i % 11) as f32 / 11.0, (i * 3 % 13) as f32 / 13.0]).collect();
        RgbdFrame {
            colour: Image { width: side, height: side, data: colour },
            depth_m: Image { width: side, height: side, data: vec![depth; n] },
        }
    }

    #[test]
    fn a_band_moved_by_part_of_a_cell_matches_at_that_pixel_offset_and_is_pasted_from_there() {
        let (side, f) = (16u32, 4usize);
        let w = side as usize;
        let base = textured(side, 5.0);
        let bank = CodeBank { rows: 4, cols: 4, n_embed: 1, codebook_crc32: 0, codes: vec![0; 16] };
        let pixels = BankPixels { bases: vec![base.clone()], roll_cells: [0, 0] };
        // the frame: the base moved 2 pixels right, twice as far away
        let mut frame = textured(side, 10.0);
        for y in 0..w {
            for x in 2..w {
                frame.colour.data[y * w + x] = base.colour.data[y * w + x - 2];
            }
        }
        let band = [5, 6, 9, 10];
        let at = |offset| band_pixel_distance(&frame, &bank, &pixels, f, (0, [0, 0], offset), &band, &[None; 4], 1);
        assert_eq!(at([0, -2]), 0.0);
        assert!(at([0, 0]) > 0.05, "{}", at([0, 0]));
        // a band cell pasted before has its source's pixels, at its offset
        let pasted = [None, None, None, Some(Pasted { frame: 0, cell: 10, offset_px: [0, -2] })];
        let d = band_pixel_distance(&frame, &bank, &pixels, f, (0, [0, 0], [0, -2]), &band, &pasted, 1);
        assert_eq!(d, 0.0);
        // by blocks' means, in step it is still 0, and a texture out of step costs less than
        // pixel by pixel
        let blocks = |offset| band_pixel_distance(&frame, &bank, &pixels, f, (0, [0, 0], offset), &band, &[None; 4], 2);
        assert_eq!(blocks([0, -2]), 0.0);
        assert!(blocks([0, -1]) < at([0, -1]), "{} {}", blocks([0, -1]), at([0, -1]));
        // cell 10 missing, pasted from the same cell 2 pixels left, at the depth around it
        let missing: Vec<bool> = (0..w * w).map(|p| (p / w) / f == 2 && (p % w) / f == 2).collect();
        let mut out = frame.clone();
        for (p, m) in missing.iter().enumerate() {
            if *m {
                out.colour.data[p] = [1.0, 0.0, 1.0];
                out.depth_m.data[p] = 0.0;
            }
        }
        let draw = BankDraw { frame: 0, shift: [0, 0], score: 0.0, cells: 1, hole: 0, offset_px: [0, -2] };
        let fill = BankFill { draws: vec![draw], deferred: vec![], sources: vec![[10, 0, 10]] };
        let hole = out.clone();
        paste_sources(&mut out, &missing, &fill, &bank, &pixels, f, true);
        assert_eq!(out.colour.data, frame.colour.data);
        assert!(out.depth_m.data.iter().all(|d| (d - 10.0).abs() < 1e-5));
        // where the offset reaches a source pixel without depth, the cell's own pixel is taken
        let mut holed = pixels.clone();
        for y in 0..w {
            holed.bases[0].depth_m.data[y * w + 6] = 0.0;
        }
        let mut out = hole;
        paste_sources(&mut out, &missing, &fill, &bank, &holed, f, true);
        for y in 8..12 {
            assert_eq!(out.colour.data[y * w + 8], base.colour.data[y * w + 8], "row {y}");
            assert_eq!(out.colour.data[y * w + 9], base.colour.data[y * w + 7], "row {y}");
        }
        assert!(out.depth_m.data.iter().all(|d| (d - 10.0).abs() < 1e-5));
    }
}
