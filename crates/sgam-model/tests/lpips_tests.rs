#![allow(clippy::unwrap_used, clippy::expect_used)]
//! LPIPS with user-supplied weights: the tests write a weight file of random VGG16/LPIPS weights
//! of the right shapes, load it, and check the distance's properties, its agreement with a
//! direct (loop-based) evaluation of LPIPS v0.1, its gradient and the loader's errors.

use std::collections::BTreeMap;
use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_model::burn::tensor::{Distribution, Tensor, TensorData};
use sgam_model::lpips::{expected_tensors, Lpips};
use sgam_model::params::{to_safetensors_bytes, NamedTensor, WeightPrecision};
use sgam_model::{default_device, ModelError};

/// Random weights of the right shapes: He-scaled conv weights (activations stay O(1) through 13
/// layers), small biases, non-negative linear heads (as trained LPIPS heads are).
fn random_weights(seed: u64) -> BTreeMap<String, NamedTensor> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    expected_tensors()
        .into_iter()
        .map(|(name, shape)| {
            let n: usize = shape.iter().product();
            let values: Vec<f32> = if name.starts_with("lin") {
                (0..n).map(|_| rng.random_range(0.0f32..0.2)).collect()
            } else if name.ends_with(".bias") {
                (0..n).map(|_| rng.random_range(-0.05f32..0.05)).collect()
            } else {
                let fan_in: usize = shape[1..].iter().product();
                let b = (6.0 / fan_in as f32).sqrt();
                (0..n).map(|_| rng.random_range(-b..b)).collect()
            };
            (name, NamedTensor { shape, values })
        })
        .collect()
}

fn write_weights(path: &Path, tensors: &BTreeMap<String, NamedTensor>) {
    std::fs::write(path, to_safetensors_bytes(tensors, WeightPrecision::F32, None).unwrap()).unwrap();
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().unwrap()
}

/// `b` random RGB images in `[-1, 1]`, `[b, 3, s, s]` row-major.
fn image(seed: u64, b: usize, s: usize) -> Vec<f32> {
    image_hw(seed, b, s, s)
}

fn image_hw(seed: u64, b: usize, h: usize, w: usize) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..b * 3 * h * w).map(|_| rng.random_range(-1.0f32..1.0)).collect()
}

fn tensor(v: &[f32], b: usize, s: usize) -> Tensor<4> {
    tensor_hw(v, b, s, s)
}

fn tensor_hw(v: &[f32], b: usize, h: usize, w: usize) -> Tensor<4> {
    Tensor::from_data(TensorData::new(v.to_vec(), [b, 3, h, w]), &default_device())
}

// --- a direct evaluation of LPIPS v0.1 on one image, plain loops in f64 ---------------------

/// `[C, H, W]` feature map.
struct Map {
    c: usize,
    h: usize,
    w: usize,
    v: Vec<f64>,
}

fn conv3x3_relu(x: &Map, weight: &NamedTensor, bias: &NamedTensor) -> Map {
    let (co, ci) = (weight.shape[0], weight.shape[1]);
    assert_eq!(ci, x.c);
    let mut v = vec![0.0f64; co * x.h * x.w];
    for o in 0..co {
        for y in 0..x.h {
            for xx in 0..x.w {
                let mut acc = bias.values[o] as f64;
                for i in 0..ci {
                    for ky in 0..3 {
                        for kx in 0..3 {
                            let (sy, sx) = (y as isize + ky as isize - 1, xx as isize + kx as isize - 1);
                            if sy < 0 || sx < 0 || sy >= x.h as isize || sx >= x.w as isize {
                                continue;
                            }
                            let wv = weight.values[((o * ci + i) * 3 + ky) * 3 + kx] as f64;
                            acc += wv * x.v[(i * x.h + sy as usize) * x.w + sx as usize];
                        }
                    }
                }
                v[(o * x.h + y) * x.w + xx] = acc.max(0.0);
            }
        }
    }
    Map { c: co, h: x.h, w: x.w, v }
}

fn max_pool2(x: &Map) -> Map {
    let (h, w) = (x.h / 2, x.w / 2);
    let mut v = vec![0.0; x.c * h * w];
    for c in 0..x.c {
        for y in 0..h {
            for xx in 0..w {
                let at = |dy: usize, dx: usize| x.v[(c * x.h + 2 * y + dy) * x.w + 2 * xx + dx];
                v[(c * h + y) * w + xx] = at(0, 0).max(at(0, 1)).max(at(1, 0)).max(at(1, 1));
            }
        }
    }
    Map { c: x.c, h, w, v }
}

fn vgg_taps(img: &[f32], h: usize, w: usize, wts: &BTreeMap<String, NamedTensor>) -> Vec<Map> {
    let shift = [-0.030, -0.088, -0.188];
    let scale = [0.458, 0.448, 0.450];
    let v = (0..3 * h * w).map(|k| (img[k] as f64 - shift[k / (h * w)]) / scale[k / (h * w)]).collect();
    let mut x = Map { c: 3, h, w, v };
    let stages: [&[usize]; 5] = [&[0, 2], &[5, 7], &[10, 12, 14], &[17, 19, 21], &[24, 26, 28]];
    let mut taps = Vec::new();
    for (k, convs) in stages.iter().enumerate() {
        if k > 0 {
            x = max_pool2(&x);
        }
        for i in *convs {
            x = conv3x3_relu(&x, &wts[&format!("features.{i}.weight")], &wts[&format!("features.{i}.bias")]);
        }
        taps.push(Map { c: x.c, h: x.h, w: x.w, v: x.v.clone() });
    }
    taps
}

/// LPIPS v0.1 of one `[3, h, w]` image pair, following the `lpips` package step by step.
fn reference_lpips(a: &[f32], b: &[f32], h: usize, w: usize, wts: &BTreeMap<String, NamedTensor>) -> f64 {
    let (ta, tb) = (vgg_taps(a, h, w, wts), vgg_taps(b, h, w, wts));
    let mut total = 0.0;
    for (k, (fa, fb)) in ta.iter().zip(&tb).enumerate() {
        let lin = &wts[&format!("lin{k}.model.1.weight")].values;
        let hw = fa.h * fa.w;
        let mut layer = 0.0;
        for p in 0..hw {
            let norm = |f: &Map| (0..f.c).map(|c| f.v[c * hw + p].powi(2)).sum::<f64>().sqrt() + 1e-10;
            let (na, nb) = (norm(fa), norm(fb));
            layer +=
                (0..fa.c).map(|c| lin[c] as f64 * (fa.v[c * hw + p] / na - fb.v[c * hw + p] / nb).powi(2)).sum::<f64>();
        }
        total += layer / hw as f64;
    }
    total
}

// --- tests ----------------------------------------------------------------------------------

#[test]
fn lpips_expected_tensor_names_are_torchvision_and_lpips_names() {
    let names: BTreeMap<String, Vec<usize>> = expected_tensors().into_iter().collect();
    assert_eq!(names.len(), 13 * 2 + 5);
    assert_eq!(names["features.0.weight"], [64, 3, 3, 3]);
    assert_eq!(names["features.28.bias"], [512]);
    assert_eq!(names["features.17.weight"], [512, 256, 3, 3]);
    assert_eq!(names["lin2.model.1.weight"], [1, 256, 1, 1]);
    assert_eq!(names["lin4.model.1.weight"], [1, 512, 1, 1]);
    assert!(!names.contains_key("features.4.weight"), "index 4 is a max-pool");
}

#[test]
fn lpips_is_zero_on_equal_images_positive_and_symmetric_otherwise() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("lpips_vgg.safetensors");
    write_weights(&path, &random_weights(1));
    let lpips = Lpips::load(&path).unwrap();
    let (b, s) = (2, 32);
    let (x, y) = (tensor(&image(10, b, s), b, s), tensor(&image(11, b, s), b, s));

    let same = values(lpips.forward(x.clone(), x.clone()));
    assert_eq!(same.len(), 1);
    assert!(same[0].abs() < 1e-6, "LPIPS(x, x) = {}", same[0]);
    let xy = values(lpips.forward(x.clone(), y.clone()))[0];
    let yx = values(lpips.forward(y.clone(), x.clone()))[0];
    assert!(xy > 1e-3, "LPIPS(x, y) = {xy}");
    assert!((xy - yx).abs() <= 1e-5 * xy, "not symmetric: {xy} vs {yx}");
    // the batch value is the mean of the per-image values, which are all positive
    let per = values(lpips.forward_per_image(x.clone(), y.clone()));
    assert_eq!(per.len(), b);
    assert!(per.iter().all(|v| *v > 0.0), "{per:?}");
    assert!((per.iter().sum::<f32>() / b as f32 - xy).abs() <= 1e-5 * xy);
    // a small perturbation is closer than an unrelated image
    let near = x.clone() + Tensor::random([b, 3, s, s], Distribution::Uniform(-0.02, 0.02), &default_device());
    let xn = values(lpips.forward(x.clone(), near))[0];
    assert!(xn > 0.0 && xn < xy, "LPIPS(x, x + noise) = {xn}, LPIPS(x, y) = {xy}");
    // bad shapes are an error from try_forward
    assert!(lpips.try_forward(x.clone(), tensor(&image(12, 1, s), 1, s)).is_err());
    assert!(lpips.try_forward(tensor(&image(12, 1, 8), 1, 8), tensor(&image(13, 1, 8), 1, 8)).is_err());
    assert!(lpips.try_forward(x, y).is_ok());
}

#[test]
fn lpips_matches_a_direct_evaluation() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("lpips_vgg.safetensors");
    let wts = random_weights(2);
    write_weights(&path, &wts);
    let lpips = Lpips::load(&path).unwrap();
    // 16x16 reaches relu5_3 at 1x1 (two images: batch handling); 20x18 pools odd sizes down
    // with the floor (20x18 -> 10x9 -> 5x4 -> 2x2 -> 1x1)
    for (b, h, w) in [(2, 16, 16), (1, 20, 18)] {
        let (a, c) = (image_hw(20, b, h, w), image_hw(21, b, h, w));
        let per = values(lpips.forward_per_image(tensor_hw(&a, b, h, w), tensor_hw(&c, b, h, w)));
        assert_eq!(per.len(), b);
        let n = 3 * h * w;
        for i in 0..b {
            let want = reference_lpips(&a[i * n..(i + 1) * n], &c[i * n..(i + 1) * n], h, w, &wts);
            let got = per[i] as f64;
            assert!(want > 1e-3, "degenerate reference {want}");
            assert!((got - want).abs() <= 1e-4 * want, "{h}x{w} image {i}: {got} vs reference {want}");
        }
    }
}

#[test]
fn lpips_is_differentiable_with_frozen_weights() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("lpips_vgg.safetensors");
    write_weights(&path, &random_weights(3));
    let device = default_device().autodiff();
    let lpips = Lpips::load_on(&path, &device).unwrap();
    let s = 32;
    let x = Tensor::<4>::from_data(TensorData::new(image(30, 1, s), [1, 3, s, s]), &device).require_grad();
    let y = Tensor::<4>::from_data(TensorData::new(image(31, 1, s), [1, 3, s, s]), &device);
    let loss = lpips.forward(x.clone(), y.clone());
    let grads = loss.backward();
    let g = values(x.grad(&grads).expect("gradient w.r.t. the image"));
    assert!(g.iter().all(|v| v.is_finite()));
    let norm = g.iter().map(|v| v * v).sum::<f32>().sqrt();
    assert!(norm > 0.0, "zero gradient");
    assert!(lpips.lin[0].weight.val().grad(&grads).is_none(), "LPIPS weights must stay frozen");
    // a step of length h against the gradient lowers the distance by about h |g| (first order)
    let h = 1e-2;
    let step: Vec<f32> = g.iter().map(|v| -h * v / norm).collect();
    let step = Tensor::from_data(TensorData::new(step, [1, 3, s, s]), &device);
    let before = values(loss.detach())[0];
    let after = values(lpips.forward(x.detach() + step, y))[0];
    let ratio = (before - after) / (h * norm);
    assert!((0.7..1.3).contains(&ratio), "descending the gradient: {before} -> {after}, {ratio} x predicted");
}

#[test]
fn lpips_load_errors_name_the_file_and_tensor() {
    let tmp = tempfile::tempdir().unwrap();
    let full = random_weights(4);

    let mut missing = full.clone();
    missing.remove("lin3.model.1.weight");
    let path = tmp.path().join("no-lin3.safetensors");
    write_weights(&path, &missing);
    let err = Lpips::load(&path).unwrap_err().to_string();
    assert!(err.contains("no-lin3.safetensors") && err.contains("lin3.model.1.weight"), "{err}");
    assert!(!err.contains("features."), "only the missing tensor is reported: {err}");

    let mut wrong = full.clone();
    wrong.insert(
        "features.10.weight".into(),
        NamedTensor { shape: vec![256, 128, 1, 9], values: vec![0.0; 256 * 128 * 9] },
    );
    let path = tmp.path().join("bad-shape.safetensors");
    write_weights(&path, &wrong);
    let err = Lpips::load(&path).unwrap_err();
    assert!(matches!(err.innermost(), ModelError::WeightsMismatch { .. }), "{err:?}");
    let err = err.to_string();
    assert!(err.contains("bad-shape.safetensors") && err.contains("features.10.weight"), "{err}");
    assert!(err.contains("[256, 128, 3, 3]"), "expected shape named: {err}");

    let path = tmp.path().join("garbage.safetensors");
    std::fs::write(&path, b"not a safetensors file").unwrap();
    let err = Lpips::load(&path).unwrap_err().to_string();
    assert!(err.contains("garbage.safetensors"), "{err}");

    let path = tmp.path().join("absent.safetensors");
    let err = Lpips::load(&path).unwrap_err().to_string();
    assert!(err.contains("absent.safetensors"), "{err}");

    // extra tensors (VGG's classifier) are ignored
    let mut extra = full;
    extra.insert("classifier.0.bias".into(), NamedTensor { shape: vec![4], values: vec![0.0; 4] });
    let path = tmp.path().join("with-classifier.safetensors");
    write_weights(&path, &extra);
    assert!(Lpips::load(&path).is_ok());
}
