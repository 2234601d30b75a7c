//! The context transformer ([`crate::context::CodeContext`]) in the CPU kernels: its dense
//! layers are the convolution kernel's `k = 1` case over tokens as pixels, attention packs each
//! head's keys and values as such a layer's weights per call, and layer norms, the depthwise
//! grid convolution, softmax and GELU are plain loops over rows (16-lane `exp`) on the calling
//! thread (a window is at most a few hundred tokens: a parallel region would cost more than
//! it saves); the heads of an attention run in parallel. Equal to
//! burn's forward pass to float rounding (tested below).

use rayon::prelude::*;
use wide::f32x16;

use super::{ConvW, LANES};
use crate::context::{CellState, CodeContext, ContextBlock, Dense, RowNorm};
use crate::quantize::to_host;
use crate::ModelError;

/// A layer norm's scale and shift.
#[derive(Debug)]
struct RowNormW {
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl RowNormW {
    fn new(n: &RowNorm) -> Result<Self, ModelError> {
        Ok(Self { weight: to_host(n.weight.val())?, bias: to_host(n.bias.val())? })
    }

    /// Normalises each row of `x` (`[n, d]`) over its `d` values (eps 1e-5, as burn's).
    fn run(&self, x: &[f32], d: usize) -> Vec<f32> {
        let mut out = vec![0.0f32; x.len()];
        out.chunks_mut(d).zip(x.chunks(d)).for_each(|(o, r)| {
            let mean = r.iter().sum::<f32>() / d as f32;
            let var = r.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d as f32;
            let inv = 1.0 / (var + 1e-5).sqrt();
            for (((o, v), w), b) in o.iter_mut().zip(r).zip(&self.weight).zip(&self.bias) {
                *o = (v - mean) * inv * w + b;
            }
        });
        out
    }
}

fn dense(d: &Dense) -> Result<ConvW, ModelError> {
    let w = to_host(d.weight.val())?;
    let [cout, cin] = d.weight.val().dims();
    let b = to_host(d.bias.val())?;
    Ok(ConvW::from_host(&w, [cout, cin, 1], Some(&b), 1, [0; 4]))
}

#[derive(Debug)]
struct Block {
    /// Depthwise taps, `[9][d]` (tap-major), and bias `[d]`.
    pos_w: Vec<f32>,
    pos_b: Vec<f32>,
    norm1: RowNormW,
    qkv: ConvW,
    proj: ConvW,
    norm2: RowNormW,
    fc1: ConvW,
    fc2: ConvW,
}

impl Block {
    fn new(b: &ContextBlock) -> Result<Self, ModelError> {
        let taps = to_host(b.pos.weight.val())?; // [d, 3, 3]
        let d = taps.len() / 9;
        let mut pos_w = vec![0.0f32; 9 * d];
        for c in 0..d {
            for t in 0..9 {
                pos_w[t * d + c] = taps[c * 9 + t];
            }
        }
        Ok(Self {
            pos_w,
            pos_b: to_host(b.pos.bias.val())?,
            norm1: RowNormW::new(&b.norm1)?,
            qkv: dense(&b.qkv)?,
            proj: dense(&b.proj)?,
            norm2: RowNormW::new(&b.norm2)?,
            fc1: dense(&b.fc1)?,
            fc2: dense(&b.fc2)?,
        })
    }

    /// `x + depthwise3x3(x)` over the `h x w` grid of tokens (zero outside).
    fn add_positions(&self, x: &[f32], [h, w]: [usize; 2], d: usize) -> Vec<f32> {
        let mut out = vec![0.0f32; x.len()];
        out.chunks_mut(w * d).enumerate().for_each(|(y, orow)| {
            for (xx, o) in orow.chunks_exact_mut(d).enumerate() {
                let own = &x[(y * w + xx) * d..(y * w + xx + 1) * d];
                for ((o, v), b) in o.iter_mut().zip(own).zip(&self.pos_b) {
                    *o = v + b;
                }
                for dy in 0..3 {
                    for dx in 0..3 {
                        let (sy, sx) = ((y + dy).wrapping_sub(1), (xx + dx).wrapping_sub(1));
                        if sy >= h || sx >= w {
                            continue;
                        }
                        let src = &x[(sy * w + sx) * d..(sy * w + sx + 1) * d];
                        let tap = &self.pos_w[(dy * 3 + dx) * d..(dy * 3 + dx + 1) * d];
                        for ((o, v), t) in o.iter_mut().zip(src).zip(tap) {
                            *o += v * t;
                        }
                    }
                }
            }
        });
        out
    }

    fn run(&self, x: &[f32], grid: [usize; 2], d: usize, heads: usize) -> Vec<f32> {
        let n = grid[0] * grid[1];
        let x = self.add_positions(x, grid, d);
        let qkv = self.qkv.dense(&self.norm1.run(&x, d), n, None); // [n, 3d]
        let dh = d / heads;
        let scale = 1.0 / (dh as f32).sqrt();
        // the heads in parallel, each on one thread
        let per_head: Vec<Vec<f32>> = (0..heads)
            .into_par_iter()
            .map(|head| {
                let (q0, k0, v0) = (head * dh, d + head * dh, 2 * d + head * dh);
                let q: Vec<f32> =
                    (0..n).flat_map(|i| qkv[i * 3 * d + q0..i * 3 * d + q0 + dh].iter().copied()).collect();
                // q k^T / sqrt(dh): the keys as a dense layer's weights (out = key, in = channel)
                let keys = ConvW::dense_from(n, dh, |j, c| qkv[j * 3 * d + k0 + c] * scale);
                let mut scores = keys.dense_in_bands(&q, n, None, 1);
                softmax_rows(&mut scores, n);
                // softmax(scores) v: the values as weights (out = channel, in = key)
                let values = ConvW::dense_from(dh, n, |c, j| qkv[j * 3 * d + v0 + c]);
                values.dense_in_bands(&scores, n, None, 1)
            })
            .collect();
        let mut att = vec![0.0f32; n * d];
        for (head, o) in per_head.iter().enumerate() {
            for (i, row) in o.chunks_exact(dh).enumerate() {
                att[i * d + head * dh..i * d + (head + 1) * dh].copy_from_slice(row);
            }
        }
        let x = self.proj.dense(&att, n, Some(&x));
        let mut hidden = self.fc1.dense(&self.norm2.run(&x, d), n, None);
        gelu(&mut hidden);
        self.fc2.dense(&hidden, n, Some(&x))
    }
}

/// Softmax of each row of `m` (`[rows, n]`) in place.
pub(super) fn softmax_rows(m: &mut [f32], n: usize) {
    m.chunks_mut(n).for_each(|row| {
        let max = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let mut chunks = row.chunks_exact_mut(LANES);
        let m16 = f32x16::splat(max);
        let mut sum = 0.0f32;
        for c in &mut chunks {
            let mut a = [0.0f32; LANES];
            a.copy_from_slice(c);
            let e = (f32x16::new(a) - m16).exp().to_array();
            sum += e.iter().sum::<f32>();
            c.copy_from_slice(&e);
        }
        for v in chunks.into_remainder() {
            *v = (*v - max).exp();
            sum += *v;
        }
        let inv = 1.0 / sum;
        row.iter_mut().for_each(|v| *v *= inv);
    });
}

/// erf by Abramowitz & Stegun 7.1.26 (absolute error below 1.5e-7), 16 lanes.
pub(super) fn erf16(v: f32x16) -> f32x16 {
    let z = v.abs();
    let t = f32x16::ONE / (f32x16::ONE + f32x16::splat(ERF_P) * z);
    let poly = ((((f32x16::splat(ERF_A[4]) * t + ERF_A[3]) * t + ERF_A[2]) * t + ERF_A[1]) * t + ERF_A[0]) * t;
    let y = f32x16::ONE - poly * (-(z * z)).exp();
    v.simd_lt(f32x16::ZERO).select(-y, y)
}

/// [`erf16`] for one value.
pub(super) fn erf1(v: f32) -> f32 {
    let z = v.abs();
    let t = 1.0 / (1.0 + ERF_P * z);
    let poly = ((((ERF_A[4] * t + ERF_A[3]) * t + ERF_A[2]) * t + ERF_A[1]) * t + ERF_A[0]) * t;
    (1.0 - poly * (-(z * z)).exp()).copysign(v)
}

const ERF_P: f32 = 0.327_591_1;
const ERF_A: [f32; 5] = [0.254_829_6, -0.284_496_72, 1.421_413_8, -1.453_152, 1.061_405_4];

/// Exact GELU, `x (1 + erf(x / sqrt 2)) / 2`, in place ([`erf16`]).
pub(super) fn gelu(x: &mut [f32]) {
    let r = std::f32::consts::FRAC_1_SQRT_2;
    x.chunks_mut(4096).for_each(|part| {
        let mut chunks = part.chunks_exact_mut(LANES);
        for c in &mut chunks {
            let mut a = [0.0f32; LANES];
            a.copy_from_slice(c);
            let v = f32x16::new(a);
            let g = v * f32x16::splat(0.5) * (f32x16::ONE + erf16(v * r));
            c.copy_from_slice(&g.to_array());
        }
        for v in chunks.into_remainder() {
            *v = *v * 0.5 * (1.0 + erf1(*v * r));
        }
    });
}

/// [`CodeContext`]'s weights for the CPU kernels.
#[derive(Debug)]
pub(super) struct CpuContext {
    feature_in: ConvW,
    code_in: ConvW,
    /// `[3][dim]`: observed, open, revealed.
    state: Vec<f32>,
    blocks: Vec<Block>,
    norm_out: RowNormW,
    out: ConvW,
    dim: usize,
    heads: usize,
}

impl CpuContext {
    pub(super) fn new(c: &CodeContext, heads: usize) -> Result<Self, ModelError> {
        let state = to_host(c.state.val())?;
        let dim = state.len() / 3;
        if heads == 0 || !dim.is_multiple_of(heads) {
            return Err(ModelError::config("context", format!("heads {heads} must divide dim {dim}")));
        }
        Ok(Self {
            feature_in: dense(&c.feature_in)?,
            code_in: dense(&c.code_in)?,
            state,
            blocks: c.blocks.iter().map(Block::new).collect::<Result<_, _>>()?,
            norm_out: RowNormW::new(&c.norm_out)?,
            out: dense(&c.out)?,
            dim,
            heads,
        })
    }

    /// Residual code logits `[h * w, K]` ([`CodeContext::forward`]) of one window of `h x w`
    /// cells: `features` `[h * w, z]`, the cells' states, and the codebook `[K][embed]` the
    /// revealed cells' codes are read from.
    pub(super) fn residual(
        &self,
        features: &[f32],
        states: &[CellState],
        codebook: &[f32],
        [h, w]: [usize; 2],
    ) -> Result<Vec<f32>, ModelError> {
        let n = h * w;
        let (z, e, d) = (self.feature_in.cin, self.code_in.cin, self.dim);
        if states.len() != n || features.len() != n * z {
            return Err(ModelError::shape(
                "a context window",
                format!("{n} states and {} feature values for {h}x{w} cells", n * z),
                format!("{} states, {} values", states.len(), features.len()),
            ));
        }
        if n == 0 {
            return Ok(Vec::new());
        }
        let mut revealed = vec![0.0f32; n * e];
        for (i, s) in states.iter().enumerate() {
            if let CellState::Revealed(c) = s {
                let c = *c as usize;
                let Some(row) = codebook.get(c * e..(c + 1) * e) else {
                    return Err(ModelError::shape(
                        "a revealed code",
                        format!("a code of the {} in the codebook", codebook.len() / e.max(1)),
                        c,
                    ));
                };
                revealed[i * e..(i + 1) * e].copy_from_slice(row);
            }
        }
        let code_tokens = self.code_in.dense(&revealed, n, None);
        let mut x = self.feature_in.dense(features, n, Some(&code_tokens));
        for (i, s) in states.iter().enumerate() {
            let kind = match s {
                CellState::Observed => 0,
                CellState::Open => 1,
                CellState::Revealed(_) => 2,
            };
            for (v, s) in x[i * d..(i + 1) * d].iter_mut().zip(&self.state[kind * d..(kind + 1) * d]) {
                *v += s;
            }
        }
        for b in &self.blocks {
            x = b.run(&x, [h, w], d, self.heads);
        }
        Ok(self.out.dense(&self.norm_out.run(&x, d), n, None))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::context::{ContextConfig, ContextInput};
    use burn::tensor::{Distribution, Tensor};

    #[test]
    fn gelu_and_softmax_match_their_definitions() {
        // erf by its Taylor series in f64 (exact to ~1e-14 for |t| <= 2.2)
        let erf = |t: f64| {
            let (mut term, mut sum) = (t, t);
            for n in 1..80 {
                term *= -t * t / n as f64;
                sum += term / (2 * n + 1) as f64;
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        };
        let mut v: Vec<f32> = (-300..=300).map(|i| i as f32 / 100.0).collect(); // 601: a tail too
        let orig = v.clone();
        gelu(&mut v);
        for (g, x) in v.iter().zip(&orig) {
            let exact = 0.5 * *x as f64 * (1.0 + erf(*x as f64 / 2f64.sqrt()));
            assert!((*g as f64 - exact).abs() < 1e-6, "gelu({x}) = {g}, exact {exact}");
        }
        let mut far = vec![-12.0f32, 12.0];
        gelu(&mut far);
        assert!(far[0].abs() < 1e-6 && (far[1] - 12.0).abs() < 1e-5, "{far:?}");
        let mut m = vec![1.0, 2.0, 3.0, 0.0, 0.0, 0.0];
        softmax_rows(&mut m, 3);
        let e: f32 = 1.0 + 1.0f32.exp() + 2.0f32.exp();
        assert!((m[2] - 2.0f32.exp() / e).abs() < 1e-6 && (m[3] - 1.0 / 3.0).abs() < 1e-6);
    }

    #[test]
    fn the_context_equals_burns_forward_pass() {
        let device = crate::default_device();
        let cfg = ContextConfig { dim: 32, layers: 2, heads: 4, mlp_ratio: 2, window_cells: 8, margin_cells: 2 };
        let (z, e, k) = (16, 8, 48);
        // every weight moved (a fresh context's output projection is zero)
        let spread = |name: &str| if name.contains("norm") { 0.3 } else { 0.4 };
        let ctx = super::super::tests::perturbed(CodeContext::new(&cfg, z, e, k, &device), spread);
        let cpu = CpuContext::new(&ctx, cfg.heads).expect("cpu");
        let codebook = Tensor::<2>::random([k, e], Distribution::Uniform(-1.0, 1.0), &device);
        let host_codebook = to_host(codebook.clone()).expect("host");
        for (h, w) in [(5, 7), (8, 8), (1, 3)] {
            let n = h * w;
            let feats = Tensor::<2>::random([n, z], Distribution::Uniform(-1.0, 1.0), &device);
            let states: Vec<CellState> = (0..n)
                .map(|i| match i % 3 {
                    0 => CellState::Observed,
                    1 => CellState::Open,
                    _ => CellState::Revealed((i * 7 % k) as u32),
                })
                .collect();
            let ours =
                cpu.residual(&to_host(feats.clone()).expect("host"), &states, &host_codebook, [h, w]).expect("ours");
            let input = ContextInput::new(feats, &states, &codebook, [1, h, w]);
            let theirs = to_host(ctx.forward(input)).expect("host");
            let scale = theirs.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
            let diff = ours.iter().zip(&theirs).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(scale > 0.1, "a residual this small tests nothing: {scale}");
            assert!(diff <= 1e-4 * scale, "{h}x{w}: residuals differ by {diff} (range {scale})");
        }
        // a window that does not fit its states is an error
        assert!(cpu.residual(&[0.0; 16], &[CellState::Open; 2], &host_codebook, [1, 1]).is_err());
    }
}
