//! The frozen image features of the distribution metrics (KID in `sgam eval world`): the
//! compact encoder as trained in the first stages, shipped as `models/features.safetensors` and
//! kept apart from the bundled refiner so scores stay comparable when the refiner is retrained.
//! The same file is the target encoder whose codes the generative trainers learn to predict.

use crate::{packing, refiner, ModelConfig, ModelError, VqModel};

/// The feature model's weights (safetensors, f16).
pub const FEATURE_MODEL: &[u8] = include_bytes!("../../../models/features.safetensors");

/// The frozen encoder of [`FEATURE_MODEL`].
pub struct FeatureExtractor {
    model: VqModel,
    config: ModelConfig,
    device: burn::tensor::Device,
}

impl std::fmt::Debug for FeatureExtractor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FeatureExtractor").finish_non_exhaustive()
    }
}

impl FeatureExtractor {
    /// Loads the shipped feature encoder.
    pub fn new() -> Result<Self, ModelError> {
        let device = crate::default_device();
        let (model, config) = refiner::load_model_bytes(FEATURE_MODEL, None, &device)?;
        Ok(Self { model, config, device })
    }

    /// Features of one frame: per latent channel of the encoder (64 for the shipped model), the
    /// mean and the standard deviation over the latent cells, interleaved. Its sides must be
    /// multiples of the model's downsampling factor.
    pub fn features(&self, frame: &sgam_core::RgbdFrame) -> Result<Vec<f32>, ModelError> {
        let f = self.config.downsample_factor();
        if !(frame.width() as usize).is_multiple_of(f) || !(frame.height() as usize).is_multiple_of(f) {
            return Err(ModelError::shape(
                "a feature frame's size",
                format!("a multiple of {f} pixels"),
                format!("{}x{}", frame.width(), frame.height()),
            ));
        }
        let k = sgam_core::Intrinsics::from_fov_x(frame.width(), frame.height(), 1.0);
        let x = packing::pack_input(&[frame], &[None], &[k], &self.config, &self.device)?;
        let z = self.model.encode(x);
        let [_, d, h, w] = z.dims();
        let v = z.into_data().try_to_vec_as::<f32>().map_err(|e| ModelError::TensorRead(format!("{e:?}")))?;
        let n = (h * w) as f32;
        let mut out = Vec::with_capacity(2 * d);
        for c in 0..d {
            let s = &v[c * h * w..(c + 1) * h * w];
            let mean = s.iter().sum::<f32>() / n;
            let var = s.iter().map(|x| (x - mean) * (x - mean)).sum::<f32>() / n;
            out.push(mean);
            out.push(var.sqrt());
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};

    use super::*;

    #[test]
    fn features_tell_real_frames_from_smeared_ones() {
        // real frames of a held-out scene against the same frames with every colour replaced by
        // the frame's mean (a "smear"): KID between two real sets must be far below KID between
        // real and smeared
        let renderer =
            sgam_synth::Renderer::new(&sgam_synth::Scene::generate(1_000_007, &sgam_synth::SceneConfig::default()));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let frames: Vec<sgam_core::RgbdFrame> = (0..24)
            .map(|_| {
                let c = sgam_core::Vec3::new(rng.random_range(-20.0..20.0), rng.random_range(-20.0..20.0), 0.0);
                let cam = sgam_synth::blender_camera(
                    c,
                    sgam_synth::CAMERA_PITCH_RAD,
                    0.0,
                    sgam_synth::dataset_intrinsics(128),
                );
                renderer.render(&cam, &sgam_synth::RenderConfig::default()).frame
            })
            .collect();
        let smeared: Vec<sgam_core::RgbdFrame> = frames
            .iter()
            .map(|f| {
                let n = f.colour.data.len() as f32;
                let mean =
                    f.colour.data.iter().fold([0.0f32; 3], |a, c| [a[0] + c[0] / n, a[1] + c[1] / n, a[2] + c[2] / n]);
                let mut g = f.clone();
                g.colour.data.iter_mut().for_each(|c| *c = mean);
                g
            })
            .collect();
        let x = FeatureExtractor::new().unwrap();
        let feats = |s: &[sgam_core::RgbdFrame]| s.iter().map(|f| x.features(f).unwrap()).collect::<Vec<_>>();
        let (a, b, c) = (feats(&frames[..12]), feats(&frames[12..]), feats(&smeared[12..]));
        assert_eq!(a[0].len(), 128);
        let (same, different) = (sgam_metrics::kid::kid(&a, &b).unwrap(), sgam_metrics::kid::kid(&a, &c).unwrap());
        eprintln!("KID real/real {same:.5}, real/smeared {different:.5}");
        // a permutation test: pool the two sets, re-split at random, and count the splits whose
        // KID reaches the observed one. Real vs smeared: no random split comes close (the sets
        // differ); real vs real: a random split often does (they do not)
        let p_value = |x: &[Vec<f32>], y: &[Vec<f32>], observed: f64| {
            let pooled: Vec<Vec<f32>> = x.iter().chain(y).cloned().collect();
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
            let trials = 200;
            let reached = (0..trials)
                .filter(|_| {
                    let mut idx: Vec<usize> = (0..pooled.len()).collect();
                    rand::seq::SliceRandom::shuffle(idx.as_mut_slice(), &mut rng);
                    let (l, r) = idx.split_at(x.len());
                    let pick = |ix: &[usize]| ix.iter().map(|&i| pooled[i].clone()).collect::<Vec<_>>();
                    sgam_metrics::kid::kid(&pick(l), &pick(r)).unwrap() >= observed
                })
                .count();
            (reached + 1) as f64 / (trials + 1) as f64
        };
        let (p_different, p_same) = (p_value(&a, &c, different), p_value(&a, &b, same));
        assert!(p_different < 0.01, "real vs smeared: p = {p_different} (KID {different})");
        assert!(p_same > 0.05, "real vs real: p = {p_same} (KID {same})");
    }

    #[test]
    fn features_are_a_mean_and_spread_per_channel_and_tell_frames_apart() {
        let fx = FeatureExtractor::new().unwrap();
        let frame = |c: [f32; 3], z: f32| sgam_core::RgbdFrame {
            colour: sgam_core::Image::filled(64, 64, c),
            depth_m: sgam_core::Image::filled(64, 64, z),
        };
        let a = fx.features(&frame([0.8, 0.1, 0.1], 8.0)).unwrap();
        let b = fx.features(&frame([0.1, 0.2, 0.9], 12.0)).unwrap();
        assert_eq!(a.len(), 2 * fx.config.embed_dim);
        // standard deviations are never negative; two different frames get different features
        assert!(a.iter().skip(1).step_by(2).all(|s| *s >= 0.0));
        let dist: f32 = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).sum();
        assert!(dist > 1e-3, "{dist}");
        assert!(matches!(fx.features(&frame([0.5; 3], 8.0)).map(|v| v.len()), Ok(n) if n == a.len()));
        let odd = sgam_core::RgbdFrame {
            colour: sgam_core::Image::filled(60, 64, [0.5; 3]),
            depth_m: sgam_core::Image::filled(60, 64, 8.0),
        };
        assert!(fx.features(&odd).unwrap_err().to_string().contains("60x64"));
    }
}
