//! Training the context transformer ([`crate::context::CodeContext`]) in the CPU kernels.
//!
//! burn's autodiff ran the context's training at about 20 pairs a second on this machine's two
//! cores with a third of the time in its GEMM microkernel and the rest in element-wise passes,
//! copies and zeroing (`perf`, docs/MODEL.md session 25). Here the forward pass keeps what the
//! backward pass needs, and the gradients are written out by hand:
//! - every product (dense layers, their input and weight gradients, attention's scores and
//!   values) runs through the convolution kernel's `k = 1` case ([`ConvW`]), the right operand
//!   packed per call;
//! - layer norms, GELU, softmax, the depthwise grid convolution and the cross-entropy are loops
//!   over rows; the heads of every window run in parallel;
//! - every sum over rows (bias and norm gradients, the grid convolution's taps) adds fixed
//!   chunks in order, so a step does not depend on the thread count.
//!
//! The gradients equal burn's autodiff to float rounding (tested below); Adam is burn's
//! (`beta_1` 0.9, `beta_2` 0.98, epsilon 1e-8 added to the corrected second moment's root).

use std::collections::BTreeMap;

use rayon::prelude::*;
use wide::f32x16;

use super::context::{erf1, erf16, gelu, softmax_rows};
use super::{ConvW, LANES};
use crate::context::{CellState, ContextConfig};
use crate::params::NamedTensor;
use crate::ModelError;

/// Rows per chunk of a sum over rows: chunks are summed in parallel, then added in order.
const CHUNK: usize = 64;

/// One trained tensor with its gradient and Adam's moments.
#[derive(Debug, Clone)]
struct Param {
    name: String,
    shape: Vec<usize>,
    value: Vec<f32>,
    m: Vec<f32>,
    v: Vec<f32>,
}

/// Index of a dense layer's weight (`[out, in]`) and bias in [`HostContext::params`].
#[derive(Debug, Clone, Copy)]
struct DenseP {
    w: usize,
    b: usize,
    cin: usize,
    cout: usize,
}

/// Index of a layer norm's scale and shift.
#[derive(Debug, Clone, Copy)]
struct NormP {
    w: usize,
    b: usize,
}

#[derive(Debug, Clone, Copy)]
struct BlockP {
    pos_w: usize,
    pos_b: usize,
    norm1: NormP,
    qkv: DenseP,
    proj: DenseP,
    norm2: NormP,
    fc1: DenseP,
    fc2: DenseP,
}

/// Takes the context's tensors by name, checking their shapes.
struct Taker<'a> {
    tensors: &'a BTreeMap<String, NamedTensor>,
    params: Vec<Param>,
}

impl Taker<'_> {
    fn take(&mut self, name: String, shape: Vec<usize>) -> Result<usize, ModelError> {
        let t = self.tensors.get(&name).ok_or_else(|| ModelError::MissingTensor(format!("context.{name}")))?;
        if t.shape != shape {
            return Err(ModelError::shape(
                "a context tensor",
                format!("context.{name} of shape {shape:?}"),
                format!("{:?}", t.shape),
            ));
        }
        let n = t.values.len();
        self.params.push(Param { name, shape, value: t.values.clone(), m: vec![0.0; n], v: vec![0.0; n] });
        Ok(self.params.len() - 1)
    }

    fn dense(&mut self, name: &str, cin: usize, cout: usize) -> Result<DenseP, ModelError> {
        Ok(DenseP {
            w: self.take(format!("{name}.weight"), vec![cout, cin])?,
            b: self.take(format!("{name}.bias"), vec![cout])?,
            cin,
            cout,
        })
    }

    fn norm(&mut self, name: &str, d: usize) -> Result<NormP, ModelError> {
        Ok(NormP { w: self.take(format!("{name}.weight"), vec![d])?, b: self.take(format!("{name}.bias"), vec![d])? })
    }
}

/// What a layer norm's backward pass needs: the normalised rows and each row's `1 / sigma`.
#[derive(Debug, Default)]
struct NormCache {
    xhat: Vec<f32>,
    inv: Vec<f32>,
}

/// A block's activations kept for the backward pass.
#[derive(Debug, Default)]
struct BlockCache {
    /// Input `[N, d]` (the grid convolution's).
    x: Vec<f32>,
    n1: NormCache,
    a: Vec<f32>,
    qkv: Vec<f32>,
    /// Softmax of every window's and head's scores: `[n][n]` per window and head, in that order.
    probs: Vec<Vec<f32>>,
    att: Vec<f32>,
    n2: NormCache,
    c: Vec<f32>,
    /// MLP pre-activation `[N, mlp d]`.
    u: Vec<f32>,
    g: Vec<f32>,
}

/// One batch of windows as the context sees it.
#[derive(Debug)]
pub(crate) struct HostBatch<'a> {
    /// Features `[b * h * w, z]`.
    pub features: &'a [f32],
    /// States of the same cells.
    pub states: &'a [CellState],
    /// Target code of every cell (read at open cells).
    pub targets: &'a [u32],
    /// `[b, h, w]`.
    pub shape: [usize; 3],
}

/// Figures of one forward pass over the open cells.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct HostReport {
    /// Training loss (soft targets).
    pub loss: f32,
    /// Cross-entropy of the exact target, nats.
    pub ce: f32,
    /// The same for the head alone.
    pub ce_head: f32,
    /// Top-1 accuracy.
    pub acc: f32,
    /// Open cells.
    pub open: usize,
}

/// The context's weights on the host, with gradients and Adam's moments, and the frozen head.
#[derive(Debug, Clone)]
pub(crate) struct HostContext {
    params: Vec<Param>,
    feature_in: DenseP,
    code_in: DenseP,
    state: usize,
    blocks: Vec<BlockP>,
    norm_out: NormP,
    out: DenseP,
    dim: usize,
    heads: usize,
    /// Frozen code head `[K, z]`, `[K]`, and codebook `[K, e]`.
    head_w: Vec<f32>,
    head_b: Vec<f32>,
    codebook: Vec<f32>,
    /// Soft target rows `[K][K]` (row `t`: the target distribution of code `t`); empty = one-hot.
    soft: Vec<f32>,
    /// Adam steps taken.
    pub adam_steps: u64,
}

impl HostContext {
    /// From the context's tensors (names as [`crate::params::named_tensors`] gives them for a
    /// [`crate::context::CodeContext`], without the `context.` prefix), the frozen code head, the
    /// codebook (`[K, e]`), and the soft-target width (`smoothing` codebook spacings; 0 =
    /// one-hot).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        cfg: &ContextConfig,
        tensors: &BTreeMap<String, NamedTensor>,
        head_w: Vec<f32>,
        head_b: Vec<f32>,
        codebook: Vec<f32>,
        z: usize,
        smoothing: f32,
        spacing: f32,
    ) -> Result<Self, ModelError> {
        cfg.validate()?;
        let k = head_b.len();
        if k == 0 || head_w.len() != k * z || !codebook.len().is_multiple_of(k) {
            return Err(ModelError::shape(
                "the code head and codebook",
                format!("[{k}, {z}] weights and a codebook of {k} rows"),
                format!("{} weights, {} codebook values", head_w.len(), codebook.len()),
            ));
        }
        let e = codebook.len() / k;
        let (d, md) = (cfg.dim, cfg.dim * cfg.mlp_ratio);
        let mut t = Taker { tensors, params: Vec::new() };
        let feature_in = t.dense("feature_in", z, d)?;
        let code_in = t.dense("code_in", e, d)?;
        let state = t.take("state".into(), vec![3, d])?;
        let mut blocks = Vec::with_capacity(cfg.layers);
        for l in 0..cfg.layers {
            let p = format!("blocks.{l}");
            blocks.push(BlockP {
                pos_w: t.take(format!("{p}.pos.weight"), vec![d, 3, 3])?,
                pos_b: t.take(format!("{p}.pos.bias"), vec![d])?,
                norm1: t.norm(&format!("{p}.norm1"), d)?,
                qkv: t.dense(&format!("{p}.qkv"), d, 3 * d)?,
                proj: t.dense(&format!("{p}.proj"), d, d)?,
                norm2: t.norm(&format!("{p}.norm2"), d)?,
                fc1: t.dense(&format!("{p}.fc1"), d, md)?,
                fc2: t.dense(&format!("{p}.fc2"), md, d)?,
            });
        }
        let norm_out = t.norm("norm_out", d)?;
        let out = t.dense("out", d, k)?;
        let params = t.params;
        let soft = if smoothing > 0.0 && spacing > 0.0 {
            let scale = 1.0 / (smoothing * spacing);
            let mut soft = vec![0.0f32; k * k];
            soft.par_chunks_mut(k).enumerate().for_each(|(t, row)| {
                let ct = &codebook[t * e..(t + 1) * e];
                for (j, v) in row.iter_mut().enumerate() {
                    let cj = &codebook[j * e..(j + 1) * e];
                    *v = -ct.iter().zip(cj).map(|(a, b)| (a - b) * (a - b)).sum::<f32>() * scale;
                }
                softmax_rows(row, k);
            });
            soft
        } else {
            Vec::new()
        };
        Ok(Self {
            params,
            feature_in,
            code_in,
            state,
            blocks,
            norm_out,
            out,
            dim: d,
            heads: cfg.heads,
            head_w,
            head_b,
            codebook,
            soft,
            adam_steps: 0,
        })
    }

    /// The context's tensors under their names (no `context.` prefix).
    pub(crate) fn named(&self) -> BTreeMap<String, NamedTensor> {
        self.params
            .iter()
            .map(|p| (p.name.clone(), NamedTensor { shape: p.shape.clone(), values: p.value.clone() }))
            .collect()
    }

    /// Adam's moments as tensors (`m.NAME`, `v.NAME`).
    pub(crate) fn moments(&self) -> BTreeMap<String, NamedTensor> {
        let mut out = BTreeMap::new();
        for p in &self.params {
            out.insert(format!("m.{}", p.name), NamedTensor { shape: p.shape.clone(), values: p.m.clone() });
            out.insert(format!("v.{}", p.name), NamedTensor { shape: p.shape.clone(), values: p.v.clone() });
        }
        out
    }

    /// Restores Adam's moments saved by [`Self::moments`] after `steps` Adam steps.
    pub(crate) fn set_moments(&mut self, t: &BTreeMap<String, NamedTensor>, steps: u64) -> Result<(), ModelError> {
        for p in &mut self.params {
            for (key, dst) in [(format!("m.{}", p.name), &mut p.m), (format!("v.{}", p.name), &mut p.v)] {
                let src = t.get(&key).ok_or_else(|| ModelError::MissingTensor(key.clone()))?;
                if src.values.len() != dst.len() {
                    return Err(ModelError::shape(
                        "an optimizer moment",
                        format!("{key}: {} values", dst.len()),
                        src.values.len(),
                    ));
                }
                dst.copy_from_slice(&src.values);
            }
        }
        self.adam_steps = steps;
        Ok(())
    }

    fn val(&self, i: usize) -> &[f32] {
        &self.params[i].value
    }

    /// One training step on `batch` at learning rate `lr`: the gradients, then Adam.
    pub(crate) fn train_step(&mut self, batch: &HostBatch<'_>, lr: f64) -> Result<HostReport, ModelError> {
        let mut grads = self.zero_grads();
        let r = self.pass(batch, Some(&mut grads))?;
        if r.loss.is_finite() {
            self.adam(&grads, lr);
        }
        Ok(r)
    }

    /// Loss, cross-entropies and accuracy of `batch`, nothing trained.
    pub(crate) fn forward_only(&self, batch: &HostBatch<'_>) -> Result<HostReport, ModelError> {
        self.pass(batch, None)
    }

    fn zero_grads(&self) -> Vec<Vec<f32>> {
        self.params.iter().map(|p| vec![0.0; p.value.len()]).collect()
    }

    /// Loss, cross-entropies and accuracy of `batch`; with `grads`, the gradients too (added).
    fn pass(&self, batch: &HostBatch<'_>, grads: Option<&mut Vec<Vec<f32>>>) -> Result<HostReport, ModelError> {
        let train = grads.is_some();
        let [b, h, w] = batch.shape;
        let n = h * w;
        let rows = b * n;
        let (d, z, e) = (self.dim, self.feature_in.cin, self.code_in.cin);
        let k = self.head_b.len();
        if batch.features.len() != rows * z || batch.states.len() != rows || batch.targets.len() != rows {
            return Err(ModelError::shape(
                "a context batch",
                format!("{rows} cells: {} feature values, {rows} states and targets", rows * z),
                format!("{}, {}, {}", batch.features.len(), batch.states.len(), batch.targets.len()),
            ));
        }
        // tokens: features, codebook vectors of revealed cells, state vectors
        let mut revealed = vec![0.0f32; rows * e];
        for (i, s) in batch.states.iter().enumerate() {
            if let CellState::Revealed(c) = s {
                let c = *c as usize;
                let row = self
                    .codebook
                    .get(c * e..(c + 1) * e)
                    .ok_or_else(|| ModelError::shape("a revealed code", format!("a code below {k}"), c))?;
                revealed[i * e..(i + 1) * e].copy_from_slice(row);
            }
        }
        let kinds: Vec<usize> = batch.states.iter().map(|s| kind(*s)).collect();
        let code_tokens = self.dense_fwd(self.code_in, &revealed, rows);
        let mut x = self.dense_fwd(self.feature_in, batch.features, rows);
        let state = self.val(self.state);
        for (i, (r, c)) in x.chunks_mut(d).zip(code_tokens.chunks(d)).enumerate() {
            let s = &state[kinds[i] * d..(kinds[i] + 1) * d];
            for ((v, c), s) in r.iter_mut().zip(c).zip(s) {
                *v += c + s;
            }
        }
        let mut caches = Vec::with_capacity(self.blocks.len());
        for l in 0..self.blocks.len() {
            let (next, cache) = self.block_fwd(l, x, [b, h, w]);
            x = next;
            caches.push(cache);
        }
        // the open cells: the output norm, the residual logits, the head's logits
        let open: Vec<usize> = (0..rows).filter(|&i| batch.states[i] == CellState::Open).collect();
        let m = open.len();
        if m == 0 {
            return Err(ModelError::EmptyBatch("a context batch without an open cell"));
        }
        let x_open: Vec<f32> = open.iter().flat_map(|&i| x[i * d..(i + 1) * d].iter().copied()).collect();
        let (y_open, n_out) = norm_fwd(&x_open, d, self.val(self.norm_out.w), self.val(self.norm_out.b));
        let mut total = self.dense_fwd(self.out, &y_open, m);
        let f_open: Vec<f32> = open.iter().flat_map(|&i| batch.features[i * z..(i + 1) * z].iter().copied()).collect();
        let head = mm_nt(&f_open, m, &self.head_w, k, z, Some(&self.head_b));
        for (t, h) in total.iter_mut().zip(&head) {
            *t += h;
        }
        let targets: Vec<usize> = open.iter().map(|&i| batch.targets[i] as usize).collect();
        if let Some(&bad) = targets.iter().find(|&&t| t >= k) {
            return Err(ModelError::shape("a target code", format!("a code below {k}"), bad));
        }
        // log-softmax rows, the report, and d loss / d logits = (softmax - target) / m
        let lse = |row: &[f32]| {
            let max = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            max + row.iter().map(|v| (v - max).exp()).sum::<f32>().ln()
        };
        let mut report = HostReport { open: m, ..HostReport::default() };
        let mut dlogits = if train { vec![0.0f32; m * k] } else { Vec::new() };
        for (i, &t) in targets.iter().enumerate() {
            let row = &total[i * k..(i + 1) * k];
            let l = lse(row);
            let hrow = &head[i * k..(i + 1) * k];
            report.ce += l - row[t];
            report.ce_head += lse(hrow) - hrow[t];
            let best = (0..k).fold(0, |bst, j| if row[j] > row[bst] { j } else { bst });
            report.acc += (best == t) as u8 as f32;
            report.loss += match self.soft.is_empty() {
                true => l - row[t],
                false => self.soft[t * k..(t + 1) * k].iter().zip(row).map(|(p, v)| p * (l - v)).sum::<f32>(),
            };
            if train {
                let dst = &mut dlogits[i * k..(i + 1) * k];
                for (j, (g, v)) in dst.iter_mut().zip(row).enumerate() {
                    let target = match self.soft.is_empty() {
                        true => (j == t) as u8 as f32,
                        false => self.soft[t * k + j],
                    };
                    *g = ((v - l).exp() - target) / m as f32;
                }
            }
        }
        let mf = m as f32;
        (report.loss, report.ce, report.ce_head, report.acc) =
            (report.loss / mf, report.ce / mf, report.ce_head / mf, report.acc / mf);
        let Some(g) = grads else {
            return Ok(report);
        };
        // backward: output projection, output norm (open rows only)
        let dy_open = self.dense_bwd(g, self.out, &dlogits, &y_open, m, true);
        let dx_open = self.norm_bwd(g, self.norm_out, &dy_open, &n_out, d);
        let mut dx = vec![0.0f32; rows * d];
        for (j, &i) in open.iter().enumerate() {
            dx[i * d..(i + 1) * d].copy_from_slice(&dx_open[j * d..(j + 1) * d]);
        }
        for l in (0..self.blocks.len()).rev() {
            dx = self.block_bwd(g, l, dx, &caches[l], [b, h, w]);
        }
        // tokens
        self.dense_bwd(g, self.feature_in, &dx, batch.features, rows, false);
        self.dense_bwd(g, self.code_in, &dx, &revealed, rows, false);
        let mut ds = vec![0.0f32; 3 * d];
        for (r, &kd) in dx.chunks(d).zip(&kinds) {
            for (g, v) in ds[kd * d..(kd + 1) * d].iter_mut().zip(r) {
                *g += v;
            }
        }
        add(&mut g[self.state], &ds);
        Ok(report)
    }

    /// `x W^T + b` of dense layer `p` over `rows` rows.
    fn dense_fwd(&self, p: DenseP, x: &[f32], rows: usize) -> Vec<f32> {
        mm_nt(x, rows, self.val(p.w), p.cout, p.cin, Some(self.val(p.b)))
    }

    /// Adds dense layer `p`'s weight and bias gradients for `dy` (`[rows, out]`) at input `x`;
    /// returns `dx` when `input`.
    fn dense_bwd(&self, g: &mut [Vec<f32>], p: DenseP, dy: &[f32], x: &[f32], rows: usize, input: bool) -> Vec<f32> {
        let dw = mm_tn(dy, rows, p.cout, x, p.cin);
        add(&mut g[p.w], &dw);
        let db = col_sums(dy, p.cout);
        add(&mut g[p.b], &db);
        if input {
            mm_nn(dy, rows, self.val(p.w), p.cout, p.cin)
        } else {
            Vec::new()
        }
    }

    /// Adds layer norm `p`'s gradients; returns `dx`.
    fn norm_bwd(&self, g: &mut [Vec<f32>], p: NormP, dy: &[f32], cache: &NormCache, d: usize) -> Vec<f32> {
        let (dx, dw, db) = norm_bwd(dy, cache, d, self.val(p.w));
        add(&mut g[p.w], &dw);
        add(&mut g[p.b], &db);
        dx
    }

    fn block_fwd(&self, l: usize, x: Vec<f32>, [b, h, w]: [usize; 3]) -> (Vec<f32>, BlockCache) {
        let p = self.blocks[l];
        let (d, heads) = (self.dim, self.heads);
        let n = h * w;
        let rows = b * n;
        let taps = tap_major(self.val(p.pos_w), d);
        let pos_b = self.val(p.pos_b);
        let mut x1 = vec![0.0f32; rows * d];
        x1.par_chunks_mut(n * d).zip(x.par_chunks(n * d)).for_each(|(o, xi)| grid_conv(xi, o, &taps, pos_b, [h, w], d));
        let (a, n1) = norm_fwd(&x1, d, self.val(p.norm1.w), self.val(p.norm1.b));
        let qkv = self.dense_fwd(p.qkv, &a, rows);
        let dh = d / heads;
        let scale = 1.0 / (dh as f32).sqrt();
        // every window's heads in parallel
        let per: Vec<(Vec<f32>, Vec<f32>)> = (0..b * heads)
            .into_par_iter()
            .map(|wh| {
                let (win, head) = (wh / heads, wh % heads);
                let [q, kk, v] = head_slices(&qkv, win * n, n, d, head * dh, dh);
                let mut probs = mm_nt1(&q, n, &kk, n, dh, scale);
                softmax_rows(&mut probs, n);
                let o = mm_nn1(&probs, n, &v, n, dh);
                (probs, o)
            })
            .collect();
        let mut att = vec![0.0f32; rows * d];
        let mut probs = Vec::with_capacity(b * heads);
        for (wh, (pr, o)) in per.into_iter().enumerate() {
            let (win, head) = (wh / heads, wh % heads);
            for (i, r) in o.chunks_exact(dh).enumerate() {
                let at = (win * n + i) * d + head * dh;
                att[at..at + dh].copy_from_slice(r);
            }
            probs.push(pr);
        }
        let mut x2 = self.dense_fwd(p.proj, &att, rows);
        add(&mut x2, &x1);
        let (c, n2) = norm_fwd(&x2, d, self.val(p.norm2.w), self.val(p.norm2.b));
        let u = self.dense_fwd(p.fc1, &c, rows);
        let mut g = u.clone();
        gelu(&mut g);
        let mut out = self.dense_fwd(p.fc2, &g, rows);
        add(&mut out, &x2);
        (out, BlockCache { x, n1, a, qkv, probs, att, n2, c, u, g })
    }

    fn block_bwd(
        &self,
        gr: &mut [Vec<f32>],
        l: usize,
        dout: Vec<f32>,
        c: &BlockCache,
        [b, h, w]: [usize; 3],
    ) -> Vec<f32> {
        let p = self.blocks[l];
        let (d, heads) = (self.dim, self.heads);
        let n = h * w;
        let rows = b * n;
        // MLP
        let dg = self.dense_bwd(gr, p.fc2, &dout, &c.g, rows, true);
        let du = gelu_bwd(&c.u, &dg);
        let dc = self.dense_bwd(gr, p.fc1, &du, &c.c, rows, true);
        let mut dx2 = self.norm_bwd(gr, p.norm2, &dc, &c.n2, d);
        add(&mut dx2, &dout);
        // attention
        let datt = self.dense_bwd(gr, p.proj, &dx2, &c.att, rows, true);
        let dh = d / heads;
        let scale = 1.0 / (dh as f32).sqrt();
        let per: Vec<[Vec<f32>; 3]> = (0..b * heads)
            .into_par_iter()
            .map(|wh| {
                let (win, head) = (wh / heads, wh % heads);
                let [q, kk, v] = head_slices(&c.qkv, win * n, n, d, head * dh, dh);
                let probs = &c.probs[wh];
                let d_o: Vec<f32> = (0..n)
                    .flat_map(|i| {
                        datt[(win * n + i) * d + head * dh..(win * n + i) * d + (head + 1) * dh].iter().copied()
                    })
                    .collect();
                let dv = mm_tn1(probs, n, n, &d_o, dh);
                let mut ds = mm_nt1(&d_o, n, &v, n, dh, 1.0); // dP
                for (srow, prow) in ds.chunks_mut(n).zip(probs.chunks(n)) {
                    let dot: f32 = srow.iter().zip(prow).map(|(a, b)| a * b).sum();
                    for (s, p) in srow.iter_mut().zip(prow) {
                        *s = p * (*s - dot) * scale;
                    }
                }
                let dq = mm_nn1(&ds, n, &kk, n, dh);
                let dk = mm_tn1(&ds, n, n, &q, dh);
                [dq, dk, dv]
            })
            .collect();
        let mut dqkv = vec![0.0f32; rows * 3 * d];
        for (wh, parts) in per.iter().enumerate() {
            let (win, head) = (wh / heads, wh % heads);
            for (which, part) in parts.iter().enumerate() {
                for (i, r) in part.chunks_exact(dh).enumerate() {
                    let at = (win * n + i) * 3 * d + which * d + head * dh;
                    dqkv[at..at + dh].copy_from_slice(r);
                }
            }
        }
        let da = self.dense_bwd(gr, p.qkv, &dqkv, &c.a, rows, true);
        let mut dx1 = self.norm_bwd(gr, p.norm1, &da, &c.n1, d);
        add(&mut dx1, &dx2);
        // grid convolution: dx = dx1 + its transpose applied to dx1; taps and bias
        let taps = tap_major(self.val(p.pos_w), d);
        let mut dx = vec![0.0f32; rows * d];
        let tap_grads: Vec<Vec<f32>> = dx
            .par_chunks_mut(n * d)
            .zip(dx1.par_chunks(n * d))
            .zip(c.x.par_chunks(n * d))
            .map(|((o, g), xi)| grid_conv_bwd(g, xi, o, &taps, [h, w], d))
            .collect();
        let mut dtaps = vec![0.0f32; 9 * d];
        for t in &tap_grads {
            add(&mut dtaps, t);
        }
        let mut dw = vec![0.0f32; 9 * d];
        for ch in 0..d {
            for t in 0..9 {
                dw[ch * 9 + t] = dtaps[t * d + ch];
            }
        }
        add(&mut gr[p.pos_w], &dw);
        let db = col_sums(&dx1, d);
        add(&mut gr[p.pos_b], &db);
        dx
    }

    /// One Adam step at `lr` with `grads`.
    fn adam(&mut self, grads: &[Vec<f32>], lr: f64) {
        const B1: f32 = 0.9;
        const B2: f32 = 0.98;
        const EPS: f32 = 1e-8;
        self.adam_steps += 1;
        let t = self.adam_steps as i32;
        let (c1, c2) = (1.0 - B1.powi(t), 1.0 - B2.powi(t));
        let lr = lr as f32;
        self.params.par_iter_mut().zip(grads).for_each(|(p, g)| {
            for (((x, g), m), v) in p.value.iter_mut().zip(g).zip(&mut p.m).zip(&mut p.v) {
                *m = B1 * *m + (1.0 - B1) * *g;
                *v = B2 * *v + (1.0 - B2) * *g * *g;
                *x -= lr * (*m / c1) / ((*v / c2).sqrt() + EPS);
            }
        });
    }

    /// The report and gradients of `batch` by tensor name (tests).
    #[cfg(test)]
    fn grads(&self, batch: &HostBatch<'_>) -> (HostReport, BTreeMap<String, Vec<f32>>) {
        let mut g = self.zero_grads();
        let r = self.pass(batch, Some(&mut g)).expect("pass");
        (r, self.params.iter().zip(g).map(|(p, g)| (p.name.clone(), g)).collect())
    }
}

fn kind(s: CellState) -> usize {
    match s {
        CellState::Observed => 0,
        CellState::Open => 1,
        CellState::Revealed(_) => 2,
    }
}

fn add(dst: &mut [f32], src: &[f32]) {
    dst.iter_mut().zip(src).for_each(|(d, s)| *d += s);
}

/// Column sums of `x` (`[rows, c]`), chunks of [`CHUNK`] rows added in order.
fn col_sums(x: &[f32], c: usize) -> Vec<f32> {
    let parts: Vec<Vec<f32>> = x
        .par_chunks(CHUNK * c)
        .map(|part| {
            let mut s = vec![0.0f32; c];
            part.chunks(c).for_each(|r| add(&mut s, r));
            s
        })
        .collect();
    let mut s = vec![0.0f32; c];
    parts.iter().for_each(|p| add(&mut s, p));
    s
}

/// `[9][d]` taps from burn's `[d, 3, 3]`.
fn tap_major(w: &[f32], d: usize) -> Vec<f32> {
    let mut t = vec![0.0f32; 9 * d];
    for c in 0..d {
        for tap in 0..9 {
            t[tap * d + c] = w[c * 9 + tap];
        }
    }
    t
}

/// `out = x + bias + depthwise3x3(x)` over one `h x w` grid of tokens (zero outside).
fn grid_conv(x: &[f32], out: &mut [f32], taps: &[f32], bias: &[f32], [h, w]: [usize; 2], d: usize) {
    for y in 0..h {
        for xx in 0..w {
            let o = &mut out[(y * w + xx) * d..(y * w + xx + 1) * d];
            for ((o, v), b) in o.iter_mut().zip(&x[(y * w + xx) * d..(y * w + xx + 1) * d]).zip(bias) {
                *o = v + b;
            }
            for tap in 0..9 {
                let (sy, sx) = ((y + tap / 3).wrapping_sub(1), (xx + tap % 3).wrapping_sub(1));
                if sy >= h || sx >= w {
                    continue;
                }
                let src = &x[(sy * w + sx) * d..(sy * w + sx + 1) * d];
                for ((o, v), t) in o.iter_mut().zip(src).zip(&taps[tap * d..(tap + 1) * d]) {
                    *o += v * t;
                }
            }
        }
    }
}

/// The backward pass of [`grid_conv`] on one grid: `dx` written (`g`, plus the taps applied
/// to `g` transposed); returns the taps' gradients `[9][d]`.
fn grid_conv_bwd(g: &[f32], x: &[f32], dx: &mut [f32], taps: &[f32], [h, w]: [usize; 2], d: usize) -> Vec<f32> {
    dx.copy_from_slice(g);
    let mut dt = vec![0.0f32; 9 * d];
    for y in 0..h {
        for xx in 0..w {
            let gy = &g[(y * w + xx) * d..(y * w + xx + 1) * d];
            for tap in 0..9 {
                let (sy, sx) = ((y + tap / 3).wrapping_sub(1), (xx + tap % 3).wrapping_sub(1));
                if sy >= h || sx >= w {
                    continue;
                }
                let src = (sy * w + sx) * d;
                let t = &taps[tap * d..(tap + 1) * d];
                for ch in 0..d {
                    dx[src + ch] += gy[ch] * t[ch];
                    dt[tap * d + ch] += gy[ch] * x[src + ch];
                }
            }
        }
    }
    dt
}

/// Layer norm of each row (eps 1e-5, as burn's): the output and what the backward pass needs.
fn norm_fwd(x: &[f32], d: usize, w: &[f32], b: &[f32]) -> (Vec<f32>, NormCache) {
    let rows = x.len() / d;
    let mut y = vec![0.0f32; x.len()];
    let mut xhat = vec![0.0f32; x.len()];
    let mut inv = vec![0.0f32; rows];
    y.par_chunks_mut(d).zip(xhat.par_chunks_mut(d)).zip(inv.par_iter_mut()).zip(x.par_chunks(d)).for_each(
        |(((y, xh), inv), r)| {
            let mean = r.iter().sum::<f32>() / d as f32;
            let var = r.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d as f32;
            *inv = 1.0 / (var + 1e-5).sqrt();
            for ((((y, xh), v), w), b) in y.iter_mut().zip(xh.iter_mut()).zip(r).zip(w).zip(b) {
                *xh = (v - mean) * *inv;
                *y = *xh * w + b;
            }
        },
    );
    (y, NormCache { xhat, inv })
}

/// Layer norm backward: `dx`, and the scale's and shift's gradients.
fn norm_bwd(dy: &[f32], c: &NormCache, d: usize, w: &[f32]) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut dx = vec![0.0f32; dy.len()];
    dx.par_chunks_mut(d).zip(dy.par_chunks(d)).zip(c.xhat.par_chunks(d)).zip(c.inv.par_iter()).for_each(
        |(((dx, dy), xh), inv)| {
            let (mut mg, mut mgx) = (0.0f32, 0.0f32);
            for ((dy, xh), w) in dy.iter().zip(xh).zip(w) {
                mg += dy * w;
                mgx += dy * w * xh;
            }
            let (mg, mgx) = (mg / d as f32, mgx / d as f32);
            for (((dx, dy), xh), w) in dx.iter_mut().zip(dy).zip(xh).zip(w) {
                *dx = inv * (dy * w - mg - xh * mgx);
            }
        },
    );
    let dyx: Vec<f32> = dy.iter().zip(&c.xhat).map(|(a, b)| a * b).collect();
    (dx, col_sums(&dyx, d), col_sums(dy, d))
}

/// `dg * gelu'(u)`, `gelu'(u) = Phi(u) + u phi(u)`.
fn gelu_bwd(u: &[f32], dg: &[f32]) -> Vec<f32> {
    let r = std::f32::consts::FRAC_1_SQRT_2;
    let inv_sqrt_2pi = 0.398_942_3f32;
    let mut out = vec![0.0f32; u.len()];
    out.par_chunks_mut(4096).zip(u.par_chunks(4096)).zip(dg.par_chunks(4096)).for_each(|((o, u), g)| {
        let mut oc = o.chunks_exact_mut(LANES);
        let mut uc = u.chunks_exact(LANES);
        let mut gc = g.chunks_exact(LANES);
        for ((o, u), g) in (&mut oc).zip(&mut uc).zip(&mut gc) {
            let uv = f32x16::new(u.try_into().unwrap_or([0.0; LANES]));
            let gv = f32x16::new(g.try_into().unwrap_or([0.0; LANES]));
            let phi = (uv * uv * f32x16::splat(-0.5)).exp() * f32x16::splat(inv_sqrt_2pi);
            let cdf = f32x16::splat(0.5) * (f32x16::ONE + erf16(uv * r));
            o.copy_from_slice(&(gv * (cdf + uv * phi)).to_array());
        }
        for ((o, u), g) in oc.into_remainder().iter_mut().zip(uc.remainder()).zip(gc.remainder()) {
            let phi = (-0.5 * u * u).exp() * inv_sqrt_2pi;
            *o = g * (0.5 * (1.0 + erf1(u * r)) + u * phi);
        }
    });
    out
}

/// One head's queries, keys and values (`[n, dh]` each) of the window starting at row `r0`.
fn head_slices(qkv: &[f32], r0: usize, n: usize, d: usize, c0: usize, dh: usize) -> [Vec<f32>; 3] {
    std::array::from_fn(|which| {
        (0..n)
            .flat_map(|i| {
                let at = (r0 + i) * 3 * d + which * d + c0;
                qkv[at..at + dh].iter().copied()
            })
            .collect()
    })
}

/// `a b^T`: `a` `[m, k]`, `b` `[n, k]` -> `[m, n]`, plus `bias` `[n]`; rows in parallel.
fn mm_nt(a: &[f32], m: usize, b: &[f32], n: usize, k: usize, bias: Option<&[f32]>) -> Vec<f32> {
    ConvW::packed([n, k, 1], bias, 1, [0; 4], |co, ci, _| b[co * k + ci]).dense(a, m, None)
}

/// `a b`: `a` `[m, k]`, `b` `[k, n]` -> `[m, n]`; rows in parallel.
fn mm_nn(a: &[f32], m: usize, b: &[f32], k: usize, n: usize) -> Vec<f32> {
    ConvW::from_row_major(b, k, n).dense(a, m, None)
}

/// `a^T b`: `a` `[k, m]`, `b` `[k, n]` -> `[m, n]`; rows in parallel.
fn mm_tn(a: &[f32], k: usize, m: usize, b: &[f32], n: usize) -> Vec<f32> {
    mm_tn_bands(a, k, m, b, n, rayon::current_num_threads())
}

/// `a^T b` in at most `bands` bands of output rows (1: on the calling thread). `a` is read in
/// place: a tile of output rows is a run of consecutive values in each row of `a`.
fn mm_tn_bands(a: &[f32], k: usize, m: usize, b: &[f32], n: usize, bands: usize) -> Vec<f32> {
    let w = ConvW::from_row_major(b, k, n);
    let mut out = vec![0.0f32; m * n];
    if m == 0 || n == 0 {
        return out;
    }
    let band = m.div_ceil(bands.clamp(1, m));
    let run = |(bi, oband): (usize, &mut [f32])| tn_rows(&w, a, m, bi * band, oband);
    if band >= m {
        run((0, &mut out));
    } else {
        out.par_chunks_mut(band * n).enumerate().for_each(run);
    }
    out
}

/// Rows of `a` (and of the packed `b`) summed per pass of [`tn_rows`]: a pass's packed `b`
/// (`TN_BLOCK` x 4 vectors, 64 KB) and `a` (`TN_BLOCK` x the band's rows) stay in the core's
/// L2 while every tile of output rows reads them. Unblocked, a weight gradient's long sum (a
/// batch's 4,096 cells) streamed the whole packed `b` (up to 8 MB) once per tile of 6 rows.
const TN_BLOCK: usize = 256;

/// Output rows `i0..` (as many as `out` holds) of `a^T b`, `b` packed in `w`; the sum over `b`'s
/// rows in blocks of [`TN_BLOCK`], each block added to what the blocks before it left in `out`.
fn tn_rows(w: &ConvW, a: &[f32], m: usize, i0: usize, out: &mut [f32]) {
    let rows = out.len() / w.cout;
    for k0 in (0..w.cin).step_by(TN_BLOCK) {
        let ks = [k0, (k0 + TN_BLOCK).min(w.cin)];
        let mut v0 = 0;
        while v0 < w.nv {
            let left = w.nv - v0;
            if left >= 4 {
                tn_columns::<6, 4>(w, a, m, i0, rows, v0, ks, out);
                v0 += 4;
            } else if left >= 2 {
                tn_columns::<8, 2>(w, a, m, i0, rows, v0, ks, out);
                v0 += 2;
            } else {
                tn_columns::<8, 1>(w, a, m, i0, rows, v0, ks, out);
                v0 += 1;
            }
        }
    }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn tn_columns<const R: usize, const V: usize>(
    w: &ConvW,
    a: &[f32],
    m: usize,
    i0: usize,
    rows: usize,
    v0: usize,
    ks: [usize; 2],
    out: &mut [f32],
) {
    let mut r = 0;
    while r + R <= rows {
        let acc = tn_tile::<R, V>(w, a, m, i0 + r, v0, ks, tn_load(w, r, v0, ks[0], out));
        w.store(&acc, r, v0, out, None);
        r += R;
    }
    while r < rows {
        let acc = tn_tile::<1, V>(w, a, m, i0 + r, v0, ks, tn_load(w, r, v0, ks[0], out));
        w.store(&acc, r, v0, out, None);
        r += 1;
    }
}

/// What earlier blocks summed into output rows `r..r + R`, vectors `v0..v0 + V` (zero before
/// the first block, whose `k0` is 0).
#[inline(always)]
fn tn_load<const R: usize, const V: usize>(w: &ConvW, r: usize, v0: usize, k0: usize, out: &[f32]) -> [[f32x16; V]; R] {
    if k0 == 0 {
        [[f32x16::ZERO; V]; R]
    } else {
        w.load(r, v0, out)
    }
}

/// `R` output rows from `i` x `V` vectors of output columns from `v0`, summed over rows
/// `ks[0]..ks[1]` of `a` and `b` onto `acc`.
#[inline(always)]
fn tn_tile<const R: usize, const V: usize>(
    w: &ConvW,
    a: &[f32],
    m: usize,
    i: usize,
    v0: usize,
    [k0, k1]: [usize; 2],
    mut acc: [[f32x16; V]; R],
) -> [[f32x16; V]; R] {
    for (j, wrow) in w.w[k0 * w.nv..k1 * w.nv].chunks_exact(w.nv).enumerate() {
        let ci = k0 + j;
        let wv = &wrow[v0..v0 + V];
        let arow = &a[ci * m + i..ci * m + i + R];
        for r in 0..R {
            let s = f32x16::splat(arow[r]);
            for v in 0..V {
                acc[r][v] = s.mul_add(wv[v], acc[r][v]);
            }
        }
    }
    acc
}

/// [`mm_nt`] times `scale`, on the calling thread.
fn mm_nt1(a: &[f32], m: usize, b: &[f32], n: usize, k: usize, scale: f32) -> Vec<f32> {
    ConvW::packed([n, k, 1], None, 1, [0; 4], |co, ci, _| b[co * k + ci] * scale).dense_in_bands(a, m, None, 1)
}

/// [`mm_nn`] on the calling thread.
fn mm_nn1(a: &[f32], m: usize, b: &[f32], k: usize, n: usize) -> Vec<f32> {
    ConvW::from_row_major(b, k, n).dense_in_bands(a, m, None, 1)
}

/// [`mm_tn`] on the calling thread.
fn mm_tn1(a: &[f32], k: usize, m: usize, b: &[f32], n: usize) -> Vec<f32> {
    mm_tn_bands(a, k, m, b, n, 1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::context::{CodeContext, ContextInput};
    use crate::params::named_tensors;
    use burn::tensor::activation::{log_softmax, softmax};
    use burn::tensor::{Distribution, Int, Tensor, TensorData};

    fn host(t: Tensor<2>) -> Vec<f32> {
        crate::quantize::to_host(t).expect("host")
    }

    #[test]
    fn products_equal_their_definitions() {
        let val = |i: usize| ((i * 7919 % 1000) as f32 / 500.0) - 1.0;
        // (a sum longer than TN_BLOCK: a^T b in blocks, each added to the ones before)
        for (m, k, n) in [(1, 1, 1), (7, 5, 19), (13, 33, 16), (6, 64, 40), (50, 3, 70), (9, 2 * TN_BLOCK + 37, 21)] {
            let a: Vec<f32> = (0..m * k).map(val).collect(); // [m, k]
            let at: Vec<f32> = (0..k * m).map(|i| a[(i % m) * k + i / m]).collect(); // [k, m]
            let b: Vec<f32> = (0..k * n).map(|i| val(i + 5)).collect(); // [k, n]
            let bt: Vec<f32> = (0..n * k).map(|i| b[(i % k) * n + i / k]).collect(); // [n, k]
            let want: Vec<f32> =
                (0..m * n).map(|i| (0..k).map(|c| a[(i / n) * k + c] * b[c * n + i % n]).sum()).collect();
            let bias: Vec<f32> = (0..n).map(|j| j as f32).collect();
            let with_bias: Vec<f32> = want.iter().enumerate().map(|(i, v)| v + (i % n) as f32).collect();
            let close = |got: Vec<f32>, want: &[f32], what: &str| {
                assert_eq!(got.len(), want.len(), "{what} {m}x{k}x{n}");
                for (g, w) in got.iter().zip(want) {
                    assert!((g - w).abs() < 1e-4 * (1.0 + w.abs()), "{what} {m}x{k}x{n}: {g} against {w}");
                }
            };
            close(mm_nt(&a, m, &bt, n, k, Some(&bias)), &with_bias, "a b^T + bias");
            close(mm_nt1(&a, m, &bt, n, k, 2.0), &want.iter().map(|v| 2.0 * v).collect::<Vec<_>>(), "a b^T 2");
            close(mm_nn(&a, m, &b, k, n), &want, "a b");
            close(mm_nn1(&a, m, &b, k, n), &want, "a b, one thread");
            close(mm_tn(&at, k, m, &b, n), &want, "a^T b");
            close(mm_tn1(&at, k, m, &b, n), &want, "a^T b, one thread");
        }
    }

    /// Gradients of the soft-target loss through burn's autodiff and through the kernels.
    #[test]
    fn gradients_equal_burns_autodiff() {
        let cpu = crate::default_device();
        let dev = cpu.clone().autodiff();
        let cfg = ContextConfig { dim: 32, layers: 2, heads: 4, mlp_ratio: 2, window_cells: 8, margin_cells: 2 };
        let (z, e, k) = (16, 8, 40);
        let spread = |name: &str| if name.contains("norm") { 0.3 } else { 0.4 };
        let ctx = super::super::tests::perturbed(CodeContext::new(&cfg, z, e, k, &cpu), spread);
        let named = named_tensors(&ctx);
        let codebook = host(Tensor::<2>::random([k, e], Distribution::Uniform(-1.0, 1.0), &cpu));
        let head_w = host(Tensor::<2>::random([k, z], Distribution::Uniform(-0.5, 0.5), &cpu));
        let head_b = host(Tensor::<2>::random([1, k], Distribution::Uniform(-0.5, 0.5), &cpu));
        let (smoothing, spacing) = (1.0, 0.7);
        let ours =
            HostContext::new(&cfg, &named, head_w.clone(), head_b.clone(), codebook.clone(), z, smoothing, spacing)
                .expect("host context");
        let (b, h, w) = (2, 5, 6);
        let rows = b * h * w;
        let feats = host(Tensor::<2>::random([rows, z], Distribution::Uniform(-1.0, 1.0), &cpu));
        let states: Vec<CellState> = (0..rows)
            .map(|i| match i % 5 {
                0 | 3 => CellState::Open,
                1 => CellState::Observed,
                _ => CellState::Revealed((i * 7 % k) as u32),
            })
            .collect();
        let targets: Vec<u32> = (0..rows).map(|i| (i * 13 % k) as u32).collect();
        let batch = HostBatch { features: &feats, states: &states, targets: &targets, shape: [b, h, w] };
        let (report, ours_g) = ours.grads(&batch);

        // burn: the same loss (ContextTrainer's), autodiff
        let module = burn::module::Module::train(ctx);
        let t = |v: &[f32], s: [usize; 2]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), s), &dev);
        let cb = t(&codebook, [k, e]);
        let input = ContextInput::new(t(&feats, [rows, z]), &states, &cb, [b, h, w]);
        let open: Vec<usize> = (0..rows).filter(|&i| states[i] == CellState::Open).collect();
        let idx = Tensor::<1, Int>::from_data(
            TensorData::new(open.iter().map(|&i| i as i64).collect::<Vec<_>>(), [open.len()]),
            &dev,
        );
        let head =
            t(&feats, [rows, z]).select(0, idx.clone()).matmul(t(&head_w, [k, z]).transpose()) + t(&head_b, [1, k]);
        let total = log_softmax(head + module.out.forward(module.tokens(input).select(0, idx)), 1);
        let tidx = Tensor::<1, Int>::from_data(
            TensorData::new(open.iter().map(|&i| targets[i] as i64).collect::<Vec<_>>(), [open.len()]),
            &dev,
        );
        let soft = softmax(
            crate::quantize::squared_distances(cb.clone().select(0, tidx), cb)
                .neg()
                .mul_scalar(1.0 / (smoothing * spacing)),
            1,
        );
        let loss = (soft * total).sum_dim(1).mean().neg();
        let theirs_loss = crate::quantize::to_host(loss.clone()).expect("loss")[0];
        assert!((report.loss - theirs_loss).abs() < 1e-4 * theirs_loss.abs().max(1.0), "{report:?} vs {theirs_loss}");
        let grads = loss.backward();
        let mut checked = 0;
        for (name, theirs) in named_tensors_grads(&module, &grads) {
            let mine = ours_g.get(&name).unwrap_or_else(|| panic!("no gradient for {name}"));
            let scale = theirs.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
            let diff = mine.iter().zip(&theirs).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(scale > 1e-6, "{name}: a gradient this small tests nothing ({scale})");
            assert!(diff <= 2e-3 * scale, "{name}: gradients differ by {diff} (range {scale})");
            checked += 1;
        }
        assert_eq!(checked, ours_g.len(), "every tensor checked");
    }

    /// Every parameter's gradient by name, from burn's autodiff.
    fn named_tensors_grads(m: &CodeContext, g: &burn::tensor::Gradients) -> Vec<(String, Vec<f32>)> {
        fn gr<const D: usize>(p: &burn::module::Param<Tensor<D>>, g: &burn::tensor::Gradients) -> Vec<f32> {
            crate::quantize::to_host(p.val().grad(g).expect("a gradient")).expect("f32")
        }
        let mut out = Vec::new();
        let dense = |out: &mut Vec<(String, Vec<f32>)>, name: &str, d: &crate::context::Dense| {
            out.push((format!("{name}.weight"), gr(&d.weight, g)));
            out.push((format!("{name}.bias"), gr(&d.bias, g)));
        };
        let norm = |out: &mut Vec<(String, Vec<f32>)>, name: &str, n: &crate::context::RowNorm| {
            out.push((format!("{name}.weight"), gr(&n.weight, g)));
            out.push((format!("{name}.bias"), gr(&n.bias, g)));
        };
        dense(&mut out, "feature_in", &m.feature_in);
        dense(&mut out, "code_in", &m.code_in);
        out.push(("state".into(), gr(&m.state, g)));
        for (l, b) in m.blocks.iter().enumerate() {
            out.push((format!("blocks.{l}.pos.weight"), gr(&b.pos.weight, g)));
            out.push((format!("blocks.{l}.pos.bias"), gr(&b.pos.bias, g)));
            norm(&mut out, &format!("blocks.{l}.norm1"), &b.norm1);
            dense(&mut out, &format!("blocks.{l}.qkv"), &b.qkv);
            dense(&mut out, &format!("blocks.{l}.proj"), &b.proj);
            norm(&mut out, &format!("blocks.{l}.norm2"), &b.norm2);
            dense(&mut out, &format!("blocks.{l}.fc1"), &b.fc1);
            dense(&mut out, &format!("blocks.{l}.fc2"), &b.fc2);
        }
        norm(&mut out, "norm_out", &m.norm_out);
        dense(&mut out, "out", &m.out);
        out
    }
}
