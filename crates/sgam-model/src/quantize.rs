//! Vector quantization: nearest-code selection with the straight-through estimator, per-cell
//! temperature sampling in missing cells, codebook usage statistics and k-means revival of dead
//! codes.
//!
//! Loss (the SGAM authors' effective weighting):
//! `||sg(z_q) - z||^2 + beta ||z_q - sg(z)||^2` with `beta = 0.25` — the commitment term (which
//! moves the encoder) has weight 1 and the codebook term (which moves the codes) has weight beta.

use burn::tensor::Tensor;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::model::VqModel;
use crate::ModelError;

/// How a code is chosen per latent cell.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Sampling {
    /// Nearest code everywhere.
    Argmin,
    /// In missing cells, sample from `softmax(-d_k / temperature)` over the `top_k` nearest codes;
    /// nearest code in observed cells. `temperature <= 0` or `top_k <= 1` is argmin.
    Temperature {
        /// Softmax temperature (in units of squared latent distance).
        temperature: f32,
        /// Number of nearest codes considered.
        top_k: usize,
    },
}

/// Result of quantizing an encoder output.
#[derive(Debug, Clone)]
pub struct Quantized {
    /// Straight-through quantized latent `z + sg(z_q - z)`, `[B, D, h, w]`.
    pub z_q: Tensor<4>,
    /// Quantizer loss (scalar, `[1]`).
    pub loss: Tensor<1>,
    /// Chosen code per cell, row-major `[B, h, w]`.
    pub indices: Vec<u32>,
    /// Encoder features as rows `[B h w, D]` on the host (for the k-means buffer).
    pub features: Vec<f32>,
}

/// `||z_i - e_k||^2` for rows `z` `[N, D]` and codebook `e` `[K, D]`: `[N, K]` (differentiable).
pub fn squared_distances(z: Tensor<2>, e: Tensor<2>) -> Tensor<2> {
    let [k, _] = e.dims();
    let zz = z.clone().square().sum_dim(1); // [N, 1]
    let ee = e.clone().square().sum_dim(1).reshape([1, k]); // [1, K]
    zz + ee - z.matmul(e.transpose()).mul_scalar(2.0)
}

/// Squared distances `[N, K]` (row-major, host) between rows of `z` `[N, D]` and the codebook.
fn distances(z: Tensor<2>, codebook: Tensor<2>) -> Result<Vec<f32>, ModelError> {
    let [n, _] = z.dims();
    let [k, _] = codebook.dims();
    let v = to_host(squared_distances(z.detach(), codebook.detach()))?;
    debug_assert_eq!(v.len(), n * k);
    Ok(v)
}

/// Index of the smallest value of `row` (the first one on ties; 0 for an empty row).
pub(crate) fn argmin(row: &[f32]) -> usize {
    row.iter().enumerate().fold((0usize, f32::INFINITY), |best, (j, &d)| if d < best.1 { (j, d) } else { best }).0
}

pub(crate) fn to_host<const D: usize>(t: Tensor<D>) -> Result<Vec<f32>, ModelError> {
    t.into_data().try_to_vec_as::<f32>().map_err(|e| ModelError::TensorRead(format!("{e:?}")))
}

/// Chooses one code per row of the `[n, k]` distance matrix. `missing[i]` marks rows that may be
/// sampled (others take the argmin); `None` = no row is missing.
pub fn select_codes(
    dist: &[f32],
    n: usize,
    k: usize,
    missing: Option<&[bool]>,
    sampling: Sampling,
    rng: &mut ChaCha8Rng,
) -> Vec<u32> {
    let draws = |i: usize| {
        missing.is_some_and(|m| m.get(i).copied().unwrap_or(false))
            && matches!(sampling, Sampling::Temperature { temperature, top_k } if temperature > 0.0 && top_k > 1)
    };
    // the uniforms a sequential loop would draw, in its order (one per sampled row); then every
    // row in parallel
    let uniforms: Vec<f64> = (0..n).map(|i| if draws(i) { rng.random::<f64>() } else { 0.0 }).collect();
    (0..n)
        .into_par_iter()
        .map(|i| {
            let row = &dist[i * k..(i + 1) * k];
            let nearest = argmin(row);
            match sampling {
                Sampling::Temperature { temperature, top_k } if draws(i) => {
                    let mut order: Vec<usize> = (0..k).collect();
                    let top = top_k.min(k);
                    order.select_nth_unstable_by(top - 1, |a, b| row[*a].total_cmp(&row[*b]).then(a.cmp(b)));
                    let mut cand: Vec<usize> = order[..top].to_vec();
                    cand.sort_by(|a, b| row[*a].total_cmp(&row[*b]).then(a.cmp(b)));
                    let dmin = row[cand[0]];
                    let weights: Vec<f64> =
                        cand.iter().map(|&j| (-((row[j] - dmin) as f64) / temperature as f64).exp()).collect();
                    cand[draw_index_at(&weights, uniforms[i]).0] as u32
                }
                _ => nearest as u32,
            }
        })
        .collect()
}

/// Draws an index with probability proportional to `weights`, given the uniform draw `u01` (in
/// `[0, 1)`; the first index when rounding leaves the draw past the end). Returns it and the
/// weights' sum.
fn draw_index_at(weights: &[f64], u01: f64) -> (usize, f64) {
    let total: f64 = weights.iter().sum();
    let mut u = u01 * total;
    for (i, w) in weights.iter().enumerate() {
        if u < *w {
            return (i, total);
        }
        u -= w;
    }
    (0, total)
}

/// Two-level sampling over a partition of the codebook into two classes (`plain[j]`: code `j`
/// belongs to the plain class — for CLEVR, the grey ground — else to the coloured one).
///
/// In a missing row, the class is drawn with the probability the whole softmax at
/// `temperature` gives it (so how often a cell starts an object is what plain temperature
/// sampling gives), then the code within the class from the softmax at `within` over that
/// class only. `within < temperature` sharpens the choice inside a class — the likeliest
/// colours and shapes of an object, the likeliest ground — without changing how often each
/// class is drawn; `within == temperature` is plain sampling at `temperature`; `within <= 0`
/// takes the nearest code of the drawn class. Observed rows take the argmin. Returns the codes
/// and, per row, the probability of the drawn code under this two-level distribution (1 for
/// observed rows), the confidence iterative sampling commits by. `within_bias` (row-major
/// `[n, k]`, in `dist`'s units), when given, is added to each row for the draw within the class
/// only: it moves which code of the class a cell takes, not how often the class is drawn
/// ([`crate::refiner::RefinerOptions::hue_coherence`]).
#[allow(clippy::too_many_arguments)]
pub fn select_codes_by_class(
    dist: &[f32],
    n: usize,
    k: usize,
    missing: &[bool],
    temperature: f32,
    within: f32,
    plain: &[bool],
    within_bias: Option<&[f32]>,
    rng: &mut ChaCha8Rng,
) -> (Vec<u32>, Vec<f32>) {
    let t = temperature.max(1e-12) as f64;
    let tw = within as f64;
    let in_plain = |j: usize| plain.get(j).copied().unwrap_or(false);
    // as the sequential loop had it: a NaN temperature samples (at the clamped `t`)
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    let sampled = |i: usize| missing.get(i).copied().unwrap_or(false) && !(temperature <= 0.0);
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    let draws_within = !(within <= 0.0);
    // the codes of each class, in code order
    let members: [Vec<usize>; 2] = [false, true].map(|c| (0..k).filter(|&j| in_plain(j) == c).collect());
    // the uniforms a sequential loop would draw, in its order: per sampled row the class's, then
    // (drawing within the class) the code's; then every row in parallel
    let uniforms: Vec<[f64; 2]> = (0..n)
        .map(|i| match sampled(i) {
            true => [rng.random::<f64>(), if draws_within { rng.random::<f64>() } else { 0.0 }],
            false => [0.0; 2],
        })
        .collect();
    (0..n)
        .into_par_iter()
        .map(|i| {
            let row = &dist[i * k..(i + 1) * k];
            let nearest = argmin(row);
            if !sampled(i) {
                return (nearest as u32, 1.0f32);
            }
            let dmin = row[nearest] as f64;
            let (mut mass, mut cmin) = ([0.0f64; 2], [f64::INFINITY; 2]);
            let mut class_nearest: [Option<usize>; 2] = [None; 2];
            for (j, &d) in row.iter().enumerate() {
                let c = in_plain(j) as usize;
                mass[c] += (-(d as f64 - dmin) / t).exp();
                cmin[c] = cmin[c].min(d as f64);
                class_nearest[c] = match class_nearest[c] {
                    Some(b) if row[b] <= d => Some(b),
                    _ => Some(j),
                };
            }
            let total = mass[0] + mass[1];
            let class = uniforms[i][0] * total >= mass[0]; // true = plain
            let c = class as usize;
            let p_class = mass[c] / total.max(1e-300);
            let (pick, p_within) = if !draws_within {
                (class_nearest[c].unwrap_or(nearest), 1.0)
            } else {
                // the within-class draw may add a bias per code (the class's odds stay the row's)
                let d = |j: usize| row[j] as f64 + within_bias.map_or(0.0, |b| b[i * k + j] as f64);
                let low = members[c].iter().map(|&j| d(j)).fold(f64::INFINITY, f64::min);
                let weights: Vec<f64> = members[c].iter().map(|&j| (-(d(j) - low) / tw).exp()).collect();
                let (at, sum) = draw_index_at(&weights, uniforms[i][1]);
                (
                    members[c].get(at).copied().unwrap_or(nearest),
                    weights.get(at).copied().unwrap_or(1.0) / sum.max(1e-300),
                )
            };
            (pick as u32, (p_class * p_within) as f32)
        })
        .unzip()
}

/// Quantizes the encoder output `z` `[B, D, h, w]` with the model's codebook.
///
/// `missing_cells`: row-major `[B, h, w]` flags for temperature sampling (see [`Sampling`]).
pub fn quantize(
    model: &VqModel,
    z: Tensor<4>,
    sampling: Sampling,
    missing_cells: Option<&[bool]>,
    beta: f32,
    rng: &mut ChaCha8Rng,
) -> Result<Quantized, ModelError> {
    let [b, d, h, w] = z.dims();
    let device = z.device();
    let codebook = model.quantize.embedding.weight.val();
    let [k, _] = codebook.dims();
    let z_rows = z.clone().permute([0, 2, 3, 1]).reshape([b * h * w, d]);
    let dist = distances(z_rows.clone(), codebook)?;
    let indices = select_codes(&dist, b * h * w, k, missing_cells, sampling, rng);
    let z_q_rows = model.quantize.lookup(&indices, &device);
    let features = to_host(z_rows.clone().detach())?;
    let commit = (z_q_rows.clone().detach() - z_rows.clone()).square().mean();
    let codebook_term = (z_q_rows.clone() - z_rows.detach()).square().mean();
    let loss = commit + codebook_term.mul_scalar(beta);
    let z_q = z_q_rows.reshape([b, h, w, d]).permute([0, 3, 1, 2]);
    let z_q = z.clone() + (z_q - z).detach();
    Ok(Quantized { z_q, loss, indices, features })
}

/// Per-code usage statistics for dead-code detection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CodebookUsage {
    /// Training step at which each code was last selected.
    pub last_used: Vec<u64>,
    /// Selection counts since the last [`CodebookUsage::take_counts`].
    pub counts: Vec<u64>,
}

impl CodebookUsage {
    /// All codes counted as used at `step`.
    pub fn new(n_embed: usize, step: u64) -> Self {
        Self { last_used: vec![step; n_embed], counts: vec![0; n_embed] }
    }

    /// Records the codes chosen at `step`.
    pub fn record(&mut self, indices: &[u32], step: u64) {
        for &i in indices {
            if let Some(s) = self.last_used.get_mut(i as usize) {
                *s = step;
                self.counts[i as usize] += 1;
            }
        }
    }

    /// Codes not used during the last `window` steps before `step`.
    pub fn dead_codes(&self, step: u64, window: u64) -> Vec<usize> {
        self.last_used.iter().enumerate().filter(|(_, &s)| step.saturating_sub(s) >= window).map(|(i, _)| i).collect()
    }

    /// Number of codes used during the last `window` steps.
    pub fn active_count(&self, step: u64, window: u64) -> usize {
        self.last_used.len() - self.dead_codes(step, window).len()
    }

    /// Perplexity `exp(H)` of the code distribution counted since the last reset (1 = one code,
    /// `n_embed` = uniform use).
    pub fn perplexity(&self) -> f64 {
        let total: u64 = self.counts.iter().sum();
        if total == 0 {
            return 0.0;
        }
        let h: f64 = self
            .counts
            .iter()
            .filter(|&&c| c > 0)
            .map(|&c| {
                let p = c as f64 / total as f64;
                -p * p.ln()
            })
            .sum();
        h.exp()
    }

    /// Checks a stored usage record fits a codebook of `n_embed` codes (both lists that long);
    /// the message says what is wrong.
    pub fn check(&self, n_embed: usize) -> Result<(), String> {
        if self.last_used.len() != n_embed || self.counts.len() != n_embed {
            return Err(format!(
                "usage has {} last_used and {} counts entries for a codebook of {n_embed}",
                self.last_used.len(),
                self.counts.len()
            ));
        }
        Ok(())
    }

    /// Resets the counts, returning the perplexity they gave.
    pub fn take_counts(&mut self) -> f64 {
        let p = self.perplexity();
        self.counts.iter_mut().for_each(|c| *c = 0);
        p
    }
}

/// A ring buffer of recent encoder features (rows of `dim` values).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureBuffer {
    /// Row length.
    pub dim: usize,
    /// Maximum number of rows kept.
    pub capacity: usize,
    /// Row-major rows.
    pub rows: Vec<f32>,
    next: usize,
}

impl FeatureBuffer {
    /// An empty buffer.
    pub fn new(dim: usize, capacity: usize) -> Self {
        Self { dim, capacity, rows: Vec::new(), next: 0 }
    }

    /// Checks a stored buffer is consistent: rows of `dim` values, at most `capacity` of them,
    /// finite; the message says what is wrong.
    pub fn check(&self, dim: usize) -> Result<(), String> {
        if self.dim != dim || dim == 0 {
            return Err(format!("feature buffer rows have {} values, the codebook {dim}", self.dim));
        }
        if !self.rows.len().is_multiple_of(dim) || self.len() > self.capacity {
            return Err(format!(
                "feature buffer holds {} values: not whole rows of {dim}, or more than {} rows",
                self.rows.len(),
                self.capacity
            ));
        }
        if self.next >= self.capacity.max(1) {
            return Err(format!("feature buffer position {} is beyond its {} rows", self.next, self.capacity));
        }
        if let Some(bad) = crate::params::first_non_finite(&self.rows) {
            return Err(format!("feature buffer: {bad}"));
        }
        Ok(())
    }

    /// Number of rows held.
    pub fn len(&self) -> usize {
        self.rows.len() / self.dim.max(1)
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Appends rows (row-major), overwriting the oldest when full.
    pub fn push(&mut self, rows: &[f32]) {
        for row in rows.chunks_exact(self.dim) {
            if self.len() < self.capacity {
                self.rows.extend_from_slice(row);
            } else {
                let at = self.next * self.dim;
                self.rows[at..at + self.dim].copy_from_slice(row);
                self.next = (self.next + 1) % self.capacity;
            }
        }
    }
}

/// Runs `iters` Lloyd iterations of k-means with `dead.len()` centres on the buffer (centres
/// initialised from distinct random rows) and writes the centres into the `dead` rows of the
/// row-major `codebook` `[K, dim]`. Returns false (no change) when the buffer is empty.
pub fn kmeans_revive(
    codebook: &mut [f32],
    dim: usize,
    dead: &[usize],
    buffer: &FeatureBuffer,
    iters: usize,
    rng: &mut ChaCha8Rng,
) -> bool {
    let n = buffer.len();
    if n == 0 || dead.is_empty() || dim != buffer.dim {
        return false;
    }
    let k = dead.len();
    let row = |i: usize| &buffer.rows[i * dim..(i + 1) * dim];
    // Initialise from random rows (distinct while the buffer allows).
    let mut picks: Vec<usize> = (0..n).collect();
    for i in 0..k.min(n) {
        let j = rng.random_range(i..n);
        picks.swap(i, j);
    }
    let mut centres: Vec<f32> = (0..k).flat_map(|c| row(picks[c % n]).to_vec()).collect();
    for _ in 0..iters {
        let mut sums = vec![0.0f64; k * dim];
        let mut counts = vec![0usize; k];
        for i in 0..n {
            let x = row(i);
            let mut best = (0usize, f32::INFINITY);
            for c in 0..k {
                let d: f32 = centres[c * dim..(c + 1) * dim].iter().zip(x).map(|(a, b)| (a - b) * (a - b)).sum();
                if d < best.1 {
                    best = (c, d);
                }
            }
            counts[best.0] += 1;
            for (s, v) in sums[best.0 * dim..(best.0 + 1) * dim].iter_mut().zip(x) {
                *s += *v as f64;
            }
        }
        for c in 0..k {
            if counts[c] > 0 {
                for j in 0..dim {
                    centres[c * dim + j] = (sums[c * dim + j] / counts[c] as f64) as f32;
                }
            } else {
                // Empty cluster: re-seed from a random row.
                let r = rng.random_range(0..n);
                centres[c * dim..(c + 1) * dim].copy_from_slice(row(r));
            }
        }
    }
    for (c, &code) in dead.iter().enumerate() {
        if (code + 1) * dim <= codebook.len() {
            codebook[code * dim..(code + 1) * dim].copy_from_slice(&centres[c * dim..(c + 1) * dim]);
        }
    }
    true
}

/// Writes a host codebook `[K, D]` back into the model (same parameter id).
pub fn set_codebook(model: VqModel, codebook: Vec<f32>, k: usize, d: usize) -> Result<VqModel, ModelError> {
    let mut map = std::collections::BTreeMap::new();
    map.insert(
        "quantize.embedding.weight".to_string(),
        crate::params::NamedTensor { shape: vec![k, d], values: codebook },
    );
    crate::params::load_named(model, &map, true, false)
}

/// Host copy of the codebook `[K, D]` (row-major).
pub fn codebook_values(model: &VqModel) -> Result<Vec<f32>, ModelError> {
    to_host(model.quantize.embedding.weight.val().detach())
}
