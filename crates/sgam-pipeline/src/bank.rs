//! The code bank a run may complete holes from ([`sgam_model::bank`]): which one
//! ([`BankSpec`]), and how one is built from the synthetic world ([`build_bank`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use sgam_model::bank::{BankPixels, CodeBank};
use sgam_model::VqRefiner;
use sgam_synth::{blender_camera, dataset_intrinsics, RenderConfig, Renderer, Scene, SceneConfig};

use crate::{PipelineError, Result, HELD_OUT_SEED_BASE};

/// Which code bank completes the model's holes.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BankSpec {
    /// The seed's own bank for a seed from outside the synthetic world, none for a
    /// CLEVR-Infinite seed: the bundled model's context draws its holes
    /// ([`BankSpec::resolve_for`]; a run's resolved configuration never holds it).
    Auto,
    /// None: the model samples every hole's codes itself.
    #[default]
    None,
    /// The bank shipped with the bundled model (`models/bank.bin`).
    Bundled,
    /// A bank built from the seed frame itself ([`seed_bank`]): holes are quilted from the
    /// seed's own codes, so a seed from outside the synthetic world grows in its own palette.
    Seed,
    /// A bank file (`sgam train bank`).
    File(PathBuf),
}

impl std::str::FromStr for BankSpec {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Ok(match s {
            "" => return Err("empty; use none, bundled or a bank file".into()),
            "auto" => BankSpec::Auto,
            "none" => BankSpec::None,
            "bundled" => BankSpec::Bundled,
            "seed" => BankSpec::Seed,
            path => BankSpec::File(PathBuf::from(path)),
        })
    }
}

impl std::fmt::Display for BankSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BankSpec::Auto => f.write_str("auto"),
            BankSpec::None => f.write_str("none"),
            BankSpec::Bundled => f.write_str("bundled"),
            BankSpec::Seed => f.write_str("seed"),
            BankSpec::File(p) => write!(f, "{}", p.display()),
        }
    }
}

impl BankSpec {
    /// [`BankSpec::Auto`] made concrete for a run from `seed`: a seed from outside the
    /// synthetic world (Google Earth, a user's RGB-D) is quilted from itself; a CLEVR-Infinite
    /// seed takes none, the model draws its holes (with the bundled model, its context: since
    /// session 30 it beats the bundled bank on every path measured, docs/MODEL.md). Other
    /// choices stay as they are.
    pub fn resolve_for(&self, seed: &crate::SeedSpec) -> BankSpec {
        match (self, seed) {
            (BankSpec::Auto, crate::SeedSpec::Rgbd { .. } | crate::SeedSpec::GoogleEarth { .. }) => BankSpec::Seed,
            (BankSpec::Auto, _) => BankSpec::None,
            (other, _) => other.clone(),
        }
    }

    /// Whether the user named a bank (bundled, the seed's or a file).
    pub fn is_explicit(&self) -> bool {
        matches!(self, BankSpec::Bundled | BankSpec::Seed | BankSpec::File(_))
    }

    /// Whether the bank holds frames of the synthetic CLEVR-Infinite world (bundled or a file
    /// from `sgam train bank`).
    pub fn is_synthetic(&self) -> bool {
        matches!(self, BankSpec::Bundled | BankSpec::File(_))
    }

    /// Gives `refiner` the bank (none for [`BankSpec::None`] and an unresolved
    /// [`BankSpec::Auto`]), naming the file in errors; [`BankSpec::Seed`] is built from `seed`
    /// (which it needs), with the seed's pixels behind its codes.
    pub fn load_into(&self, refiner: &mut VqRefiner, seed: Option<&crate::Seed>) -> Result<()> {
        let (bank, pixels) = match (self, seed) {
            (BankSpec::None | BankSpec::Auto, _) => (None, None),
            (BankSpec::Seed, Some(seed)) => {
                let (bank, pixels) = seed_bank(refiner, &seed.frame, &seed.camera.intrinsics)?;
                (Some(bank), Some(Arc::new(pixels)))
            }
            (BankSpec::Seed, None) => {
                return Err(PipelineError::Config("--bank seed needs the seed frame to build its bank from".into()))
            }
            (BankSpec::Bundled, _) => (Some(CodeBank::from_bytes(crate::refiners::BUNDLED_BANK)?), None),
            (BankSpec::File(p), _) => (Some(CodeBank::read(p).map_err(|e| PipelineError::Model(e.in_file(p)))?), None),
        };
        refiner.set_bank(bank.map(Arc::new)).map_err(|e| match self {
            BankSpec::File(p) => PipelineError::Model(e.in_file(p)),
            _ => PipelineError::Model(e),
        })?;
        refiner.set_bank_pixels(pixels);
        Ok(())
    }

    /// The bank's [`bank_id`] (`None` without a bank): a resumed run refuses a bank that changed
    /// since it started.
    pub fn crc32(&self) -> Result<Option<u32>> {
        Ok(match self {
            // the seed's bank follows from the seed and the model, which a resume checks
            BankSpec::None | BankSpec::Auto | BankSpec::Seed => None,
            BankSpec::Bundled => Some(bank_id(crate::refiners::BUNDLED_BANK)),
            BankSpec::File(p) => {
                Some(bank_id(&std::fs::read(p).map_err(|e| sgam_io::IoError::Io { path: p.clone(), source: e })?))
            }
        })
    }
}

/// A bank file's identity: the CRC-32 of its content, i.e. without its own trailing CRC. (The
/// CRC-32 of a whole file that ends with its own CRC is the same constant, 0x2144df1c, for every
/// such file, so it cannot tell two banks apart.)
pub fn bank_id(bytes: &[u8]) -> u32 {
    crc32fast::hash(&bytes[..bytes.len().saturating_sub(4)])
}

/// First scene seed of the bank's frames: training scenes, far from the ones evaluations and
/// tuning use (11-14) and below the held-out seeds.
pub const BANK_SCENE_BASE: u64 = 500_000;
/// Frames rendered per scene.
const FRAMES_PER_SCENE: usize = 8;

/// Builds a bank of `frames` true frames at `res` x `res` px: training scenes from
/// [`BANK_SCENE_BASE`] + 8 `seed`..., the dataset's camera (height and pitch) at random positions
/// within 15 m of the scene's centre and random headings, each encoded by `refiner`'s model.
/// `progress` is called with the number of frames done.
pub fn build_bank(
    refiner: &mut VqRefiner,
    frames: usize,
    res: u32,
    seed: u64,
    mut progress: impl FnMut(usize),
) -> Result<CodeBank> {
    let f = refiner.config().downsample_factor() as u32;
    if frames == 0 || res == 0 || !res.is_multiple_of(f) {
        return Err(PipelineError::Config(format!(
            "a bank needs at least one frame and a resolution that is a multiple of {f} (got {frames} frames at {res} px)"
        )));
    }
    let k = dataset_intrinsics(res);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x0BA4 ^ seed);
    let mut codes = Vec::with_capacity(frames * (res / f * res / f) as usize);
    let scenes = frames.div_ceil(FRAMES_PER_SCENE);
    for s in 0..scenes {
        let scene_seed = BANK_SCENE_BASE + seed.wrapping_mul(scenes as u64) + s as u64;
        if scene_seed >= HELD_OUT_SEED_BASE {
            return Err(PipelineError::Config(format!(
                "--seed {seed} would draw the bank from held-out scenes (from {HELD_OUT_SEED_BASE})"
            )));
        }
        let renderer = Renderer::new(&Scene::generate(scene_seed, &SceneConfig::default()));
        for _ in 0..FRAMES_PER_SCENE.min(frames - s * FRAMES_PER_SCENE) {
            let c = sgam_core::Vec3::new(
                rng.random_range(-15.0..15.0),
                rng.random_range(-15.0..15.0),
                sgam_synth::CAMERA_HEIGHT_M,
            );
            let yaw = rng.random_range(0.0..std::f32::consts::TAU);
            let camera = blender_camera(c, sgam_synth::CAMERA_PITCH_RAD, yaw, k);
            let frame = renderer.render(&camera, &RenderConfig::default()).frame;
            let grid = refiner.frame_codes(&frame, &k)?;
            codes.extend(grid.iter().map(|&c| c as u16));
            progress(codes.len() / grid.len().max(1));
        }
    }
    let side = (res / f) as usize;
    let codebook_crc32 = refiner.codebook_crc32()?;
    Ok(CodeBank { rows: side, cols: side, n_embed: refiner.config().n_embed, codebook_crc32, codes })
}

/// Columns between two rolled copies of the seed in its bank: with the search's horizontal
/// shifts of up to 2 cells, every offset of the seed is within reach of one copy.
/// Rows and columns between two rolled copies of a seed's grid ([`CodeBank::rolled`]): with the
/// search's sideways shifts of up to 2 columns every column offset is reached; rows stay (a
/// row's depth fits the rows beside it). Rolling rows every 3 as well (session 20, 40 steps) moved
/// KID seed vs new area from 0.66 to 0.49 on Google Earth seed0, 0.07 to 0.17 on seed1, 0.46 to
/// 0.46 on seed2, and doubled the 7-Scenes frame's floating share (0.30 to 0.57): not taken.
const SEED_ROLL_CELLS: [usize; 2] = [0, 5];

/// The bank of a seed frame (`--bank seed`): the model's codes of the frame and of its mirror
/// image, each rolled sideways by every multiple of [`SEED_ROLL_CELLS`] columns
/// ([`CodeBank::rolled`]), with the two frames' pixels behind them. A hole takes the pixels of
/// the part of the seed whose surroundings match its own: the seed's palette and textures,
/// quilted (Efros & Freeman 2001), whatever the model learned. Pixels without a valid depth (a
/// real seed's holes, Google Earth's sky) are given to the model as missing.
pub fn seed_bank(
    refiner: &mut VqRefiner,
    frame: &sgam_core::RgbdFrame,
    k: &sgam_core::Intrinsics,
) -> Result<(CodeBank, BankPixels)> {
    let f = refiner.config().downsample_factor();
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    if !w.is_multiple_of(f) || !h.is_multiple_of(f) {
        return Err(PipelineError::Config(format!(
            "--bank seed: the seed is {w}x{h} px; a bank needs sides that are multiples of {f}"
        )));
    }
    let missing = |fr: &sgam_core::RgbdFrame| -> Vec<bool> {
        fr.depth_m.data.iter().map(|d| !sgam_core::is_valid_depth(*d)).collect()
    };
    let mirror = mirrored(frame);
    let mirror_k = sgam_core::Intrinsics { cx: w as f32 - 1.0 - k.cx, ..*k };
    let grids = [
        refiner.frame_codes_missing(frame, &missing(frame), k)?,
        refiner.frame_codes_missing(&mirror, &missing(&mirror), &mirror_k)?,
    ];
    let bank =
        CodeBank::rolled(&grids, [h / f, w / f], SEED_ROLL_CELLS, refiner.config().n_embed, refiner.codebook_crc32()?);
    Ok((bank, BankPixels { bases: vec![frame.clone(), mirror], roll_cells: SEED_ROLL_CELLS }))
}

/// `frame` mirrored left to right.
pub(crate) fn mirrored(frame: &sgam_core::RgbdFrame) -> sgam_core::RgbdFrame {
    let mut out = frame.clone();
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    for y in 0..h {
        out.colour.data[y * w..(y + 1) * w].reverse();
        out.depth_m.data[y * w..(y + 1) * w].reverse();
    }
    out
}

/// Writes `bank` to `path` atomically.
pub fn write_bank(path: &Path, bank: &CodeBank) -> Result<()> {
    let bytes = bank.to_bytes();
    sgam_io::write_atomic(path, |w| std::io::Write::write_all(w, &bytes))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_banks_have_different_ids_though_their_whole_file_crcs_agree() {
        let bank = |c: u16| CodeBank { rows: 1, cols: 2, n_embed: 8, codebook_crc32: 1, codes: vec![c, 1] };
        let (a, b) = (bank(2).to_bytes(), bank(3).to_bytes());
        // a file that ends with its own CRC-32 always has the same whole-file CRC-32
        assert_eq!(crc32fast::hash(&a), crc32fast::hash(&b));
        assert_ne!(bank_id(&a), bank_id(&b));
        assert_eq!(bank_id(&a), u32::from_le_bytes(a[a.len() - 4..].try_into().unwrap()));
    }
}
