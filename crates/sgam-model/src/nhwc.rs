//! The CPU inference path of the convolutional encoder and decoder (issue 26: speed that buys
//! model size).
//!
//! burn's CPU backend runs each convolution as an NCHW -> NHWC copy, an element-wise im2col with
//! a bounds check per tap, a GEMM and a scatter back to NCHW, with GroupNorm and SiLU as separate
//! passes over memory: perf put a third of the refine's time in that layout work (docs/MODEL.md,
//! session 23). Here the activations stay NHWC for the whole pass and each convolution
//! - copies its input once into a zero-padded buffer, applying on the way what precedes it in
//!   the model: GroupNorm + SiLU as one per-channel affine map and a vectorised SiLU, or the
//!   nearest x2 upsampling;
//! - accumulates all `k x k` taps of a tile of output pixels in registers: 16-lane vectors over
//!   output channels (`wide::f32x16`, AVX-512 where the build targets it, two AVX2 halves
//!   elsewhere), each input value broadcast once per tap and channel;
//! - adds bias and the residual skip in its store.
//!
//! Hand-written because no crate does this: burn (and candle) convolve through im2col + GEMM in
//! NCHW, and the inference engines that keep NHWC (tract, ort) would need the model exported to
//! ONNX and a second runtime. The context transformer also trains here ([`train`]); the
//! convolutional stages train through burn's autodiff. Models with
//! attention (the `paper` preset) are not covered and keep burn's path. Checked against burn's
//! forward pass in the tests below.

use burn::nn::conv::Conv2d;
use rayon::prelude::*;
use wide::f32x16;

use crate::blocks::{Norm, ResnetBlock};
use crate::config::ModelConfig;
use crate::context::CellState;
use crate::model::{Mid, VqModel};
use crate::quantize::to_host;
use crate::ModelError;

mod context;
pub(crate) mod train;

/// Lanes of one vector of output channels.
const LANES: usize = 16;

/// One image's activations, NHWC: `h x w x c` values, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Act {
    /// Rows.
    pub h: usize,
    /// Columns.
    pub w: usize,
    /// Channels.
    pub c: usize,
    /// `h * w * c` values, channels fastest.
    pub data: Vec<f32>,
    /// Per channel, the sum and the sum of squares of its values (f64), where the convolution
    /// that made it kept them (what a following GroupNorm needs; added row by row in row order,
    /// so they do not depend on the thread count). Not public: data changed outside would make
    /// them stale.
    pub(crate) sums: Option<Vec<[f64; 2]>>,
}

impl Act {
    /// From one image's planes (`c x h x w`, NCHW without the batch).
    pub fn from_nchw(values: &[f32], c: usize, h: usize, w: usize) -> Self {
        let hw = h * w;
        let mut data = vec![0.0; hw * c];
        if c > 0 && w > 0 && values.len() >= hw * c {
            data.par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
                for (x, px) in row.chunks_exact_mut(c).enumerate() {
                    for (ch, v) in px.iter_mut().enumerate() {
                        *v = values[ch * hw + y * w + x];
                    }
                }
            });
        }
        Self { h, w, c, data, sums: None }
    }
}

/// What a convolution applies to its input while copying it into the padded buffer.
#[derive(Debug, Clone, Copy)]
enum Pre<'a> {
    /// Nothing.
    Copy,
    /// `silu(x * scale[c] + shift[c])`: a GroupNorm folded into per-channel affine maps.
    NormSilu(&'a [f32], &'a [f32]),
    /// Nearest-neighbour x2 upsampling.
    Up2,
}

/// A convolution's weights, laid out for the kernel: per tap, per input channel, the output
/// channels in vectors of 16 (zero-padded).
#[derive(Debug)]
struct ConvW {
    k: usize,
    stride: usize,
    /// Zero padding: top, left, bottom, right.
    pad: [usize; 4],
    cin: usize,
    cout: usize,
    /// Vectors of output channels (`cout / 16` rounded up).
    nv: usize,
    /// `[k * k][cin][nv]`.
    w: Vec<f32x16>,
    /// `[nv]`.
    bias: Vec<f32x16>,
}

impl ConvW {
    fn new(conv: &Conv2d, stride: usize, pad: [usize; 4]) -> Result<Self, ModelError> {
        let (host, dims, bias) = conv_host(conv)?;
        Ok(Self::from_host(&host, dims, bias.as_deref(), stride, pad))
    }

    /// From PyTorch-layout weights `[cout, cin, k, k]` (row-major) and an optional bias.
    fn from_host(
        host: &[f32],
        [cout, cin, k]: [usize; 3],
        bias_host: Option<&[f32]>,
        stride: usize,
        pad: [usize; 4],
    ) -> Self {
        let kk = k * k;
        Self::packed([cout, cin, k], bias_host, stride, pad, |co, ci, tap| host[(co * cin + ci) * kk + tap])
    }

    /// A dense layer `cin -> cout` without bias whose weight is the row-major `[cin, cout]`
    /// matrix `rows` (a product's right operand `b` in `a b`): the kernel's layout is those rows
    /// with each padded to whole vectors, so they are copied a vector at a time, not a value at a
    /// time through [`Self::packed`] (a weight gradient's `b` holds a batch's 4,096 rows).
    fn from_row_major(rows: &[f32], cin: usize, cout: usize) -> Self {
        let nv = cout.div_ceil(LANES);
        let mut w = Vec::with_capacity(cin * nv);
        for row in rows.chunks_exact(cout.max(1)).take(cin) {
            // the last vector of a row holds its tail, zero past `cout`
            for v in row.chunks(LANES) {
                let mut lanes = [0.0f32; LANES];
                lanes[..v.len()].copy_from_slice(v);
                w.push(f32x16::new(lanes));
            }
        }
        w.resize(cin * nv, f32x16::ZERO);
        Self { k: 1, stride: 1, pad: [0; 4], cin, cout, nv, w, bias: vec![f32x16::ZERO; nv] }
    }

    /// The kernel's layout of a `k x k` convolution `cin -> cout` whose weight of output `co`,
    /// input `ci` and tap `tap` (row-major over the kernel) is `weight(co, ci, tap)`.
    fn packed(
        [cout, cin, k]: [usize; 3],
        bias_host: Option<&[f32]>,
        stride: usize,
        pad: [usize; 4],
        weight: impl Fn(usize, usize, usize) -> f32,
    ) -> Self {
        let nv = cout.div_ceil(LANES);
        let mut lanes = vec![[0.0f32; LANES]; k * k * cin * nv];
        for tap in 0..k * k {
            for ci in 0..cin {
                for co in 0..cout {
                    lanes[(tap * cin + ci) * nv + co / LANES][co % LANES] = weight(co, ci, tap);
                }
            }
        }
        let mut bias = vec![[0.0f32; LANES]; nv];
        for (co, v) in bias_host.unwrap_or(&[]).iter().enumerate().take(cout) {
            bias[co / LANES][co % LANES] = *v;
        }
        Self {
            k,
            stride,
            pad,
            cin,
            cout,
            nv,
            w: lanes.into_iter().map(f32x16::new).collect(),
            bias: bias.into_iter().map(f32x16::new).collect(),
        }
    }

    /// `conv` after the 1x1 convolution `first`, as one convolution without padding: the
    /// weights composed, and `first`'s bias carried through `conv`'s taps. Exact only because
    /// there is no padding (a padded border would see `first`'s bias, not zeros).
    fn after_pointwise(conv: &Conv2d, first: &Conv2d, stride: usize) -> Result<Self, ModelError> {
        let (w2, [cout, mid, k], b2) = conv_host(conv)?;
        let (w1, [mid1, cin, k1], b1) = conv_host(first)?;
        if mid1 != mid || k1 != 1 {
            return Err(ModelError::shape(
                "a 1x1 convolution to fold into the next",
                format!("{mid} outputs, 1x1"),
                format!("{mid1} outputs, {k1}x{k1}"),
            ));
        }
        let kk = k * k;
        let mut w = vec![0.0f32; cout * cin * kk];
        let mut bias = b2.unwrap_or_else(|| vec![0.0; cout]);
        for co in 0..cout {
            for m in 0..mid {
                for tap in 0..kk {
                    let a = w2[(co * mid + m) * kk + tap];
                    for ci in 0..cin {
                        w[(co * cin + ci) * kk + tap] += a * w1[m * cin + ci];
                    }
                    if let Some(b1) = &b1 {
                        bias[co] += a * b1[m];
                    }
                }
            }
        }
        Ok(Self::from_host(&w, [cout, cin, k], Some(&bias), stride, [0; 4]))
    }

    /// The convolution with its output negated (weights and bias).
    fn negated(mut self) -> Self {
        self.w.iter_mut().chain(self.bias.iter_mut()).for_each(|v| *v = -*v);
        self
    }

    /// A `k x k` convolution with "same" padding (`k / 2` on every side), stride 1.
    fn same(conv: &Conv2d) -> Result<Self, ModelError> {
        let k = conv.weight.dims()[2];
        let p = k / 2;
        Self::new(conv, 1, [p; 4])
    }

    /// Convolves `x` after `pre`, adding `skip` (the output's shape) when given; the output
    /// keeps its per-channel sums for a following GroupNorm.
    fn run(&self, x: &Act, pre: Pre<'_>, skip: Option<&Act>) -> Act {
        self.run_with(x, pre, skip, true)
    }

    /// [`Self::run`], keeping the output's sums only when `sums`.
    ///
    /// The output rows are cut into one band per thread; each band copies the input rows it
    /// reads (its own, and the `k - 1` it shares with the next band) into its own padded buffer,
    /// so a convolution is one parallel region.
    fn run_with(&self, x: &Act, pre: Pre<'_>, skip: Option<&Act>, sums: bool) -> Act {
        let (k, s, cin, cout) = (self.k, self.stride, self.cin, self.cout);
        debug_assert_eq!(x.c, cin, "input channels");
        if k == 1 && s == 1 && self.pad == [0; 4] && matches!(pre, Pre::Copy) {
            // a pointwise convolution reads its input in place: all pixels as one row of a
            // dense layer (no padded copy, no row tails)
            let n = x.h * x.w;
            let data = self.dense(&x.data, n, skip.map(|a| a.data.as_slice()));
            let sums =
                sums.then(|| add_rows(data.chunks(x.w.max(1) * cout).map(|r| channel_sums(r, cout, None)), cout));
            return Act { h: x.h, w: x.w, c: cout, data, sums };
        }
        let (ih, iw) = match pre {
            Pre::Up2 => (2 * x.h, 2 * x.w),
            _ => (x.h, x.w),
        };
        let [pt, pl, pb, pr] = self.pad;
        let (ph, pw) = (ih + pt + pb, iw + pl + pr);
        if ph < k || pw < k {
            return Act { h: 0, w: 0, c: cout, data: Vec::new(), sums: None };
        }
        let (oh, ow) = ((ph - k) / s + 1, (pw - k) / s + 1);
        let rs = pw * cin;
        // per-channel maps tiled over a row, so a row is one flat loop
        let (row_scale, row_shift): (Vec<f32>, Vec<f32>) = match pre {
            Pre::NormSilu(scale, shift) => {
                ((0..iw * cin).map(|i| scale[i % cin]).collect(), (0..iw * cin).map(|i| shift[i % cin]).collect())
            }
            _ => (Vec::new(), Vec::new()),
        };
        let src_rs = x.w * cin;
        // padded row `py` into `dst` (a row of `pw * cin` zeros)
        let fill = |py: usize, dst: &mut [f32]| {
            if py < pt || py >= pt + ih {
                return;
            }
            let y = py - pt;
            let dst = &mut dst[pl * cin..(pl + iw) * cin];
            match pre {
                Pre::Copy => dst.copy_from_slice(&x.data[y * src_rs..(y + 1) * src_rs]),
                Pre::NormSilu(..) => norm_silu(&x.data[y * src_rs..(y + 1) * src_rs], &row_scale, &row_shift, dst),
                Pre::Up2 => {
                    let src = &x.data[(y / 2) * src_rs..(y / 2 + 1) * src_rs];
                    for (xx, px) in dst.chunks_exact_mut(cin).enumerate() {
                        px.copy_from_slice(&src[(xx / 2) * cin..(xx / 2 + 1) * cin]);
                    }
                }
            }
        };
        let ors = ow * cout;
        let bands = rayon::current_num_threads().clamp(1, oh);
        let band_rows = oh.div_ceil(bands);
        let mut out = vec![0.0f32; oh * ors];
        // per output row: the row's per-channel sums (rows summed in order below, so the sums do
        // not depend on how many bands, i.e. threads, there were)
        let band_sums: Vec<Vec<Vec<[f64; 2]>>> = out
            .par_chunks_mut(band_rows * ors)
            .enumerate()
            .map(|(b, oband)| {
                let oy0 = b * band_rows;
                let rows = oband.len() / ors;
                // the band's padded input: rows `py0..py1`, its first row local row 0
                let py0 = oy0 * s;
                let py1 = (oy0 + rows - 1) * s + k;
                let mut p = vec![0.0f32; (py1 - py0) * rs];
                for (i, prow) in p.chunks_exact_mut(rs).enumerate() {
                    fill(py0 + i, prow);
                }
                let mut row_sums = Vec::with_capacity(if sums { rows } else { 0 });
                for (r, orow) in oband.chunks_exact_mut(ors).enumerate() {
                    let oy = oy0 + r;
                    let skip_row = skip.map(|a| &a.data[oy * ors..(oy + 1) * ors]);
                    self.row(&p, rs, r, ow, orow, skip_row);
                    if sums {
                        row_sums.push(channel_sums(orow, cout, None));
                    }
                }
                row_sums
            })
            .collect();
        let sums = sums.then(|| add_rows(band_sums.into_iter().flatten(), cout));
        Act { h: oh, w: ow, c: cout, data: out, sums }
    }

    /// Every output channel of every pixel of output row `oy` (`ow` pixels) of the padded input
    /// `p` (rows of `rs` values).
    fn row(&self, p: &[f32], rs: usize, oy: usize, ow: usize, orow: &mut [f32], skip: Option<&[f32]>) {
        let mut v0 = 0;
        while v0 < self.nv {
            let left = self.nv - v0;
            if left >= 4 {
                self.columns::<6, 4>(p, rs, oy, ow, v0, orow, skip);
                v0 += 4;
            } else if left >= 2 {
                self.columns::<8, 2>(p, rs, oy, ow, v0, orow, skip);
                v0 += 2;
            } else {
                self.columns::<8, 1>(p, rs, oy, ow, v0, orow, skip);
                v0 += 1;
            }
        }
    }

    /// A dense layer (`k = 1`) over `n` rows of `x` (`[n, cin]`, row-major; the rows are the
    /// pixels of one row of a 1x1 convolution): `[n, cout]`, plus `skip` (`[n, cout]`) when
    /// given. The rows are cut into one band per thread.
    fn dense(&self, x: &[f32], n: usize, skip: Option<&[f32]>) -> Vec<f32> {
        self.dense_in_bands(x, n, skip, rayon::current_num_threads())
    }

    /// [`Self::dense`] in at most `bands` bands (1: on the calling thread only).
    fn dense_in_bands(&self, x: &[f32], n: usize, skip: Option<&[f32]>, bands: usize) -> Vec<f32> {
        let (cin, cout) = (self.cin, self.cout);
        debug_assert!(self.k == 1 && self.stride == 1 && x.len() >= n * cin, "a dense layer");
        let mut out = vec![0.0f32; n * cout];
        if n == 0 || cout == 0 {
            return out;
        }
        let band = n.div_ceil(bands.clamp(1, n));
        let run = |(b, oband): (usize, &mut [f32])| {
            let (r0, m) = (b * band, oband.len() / cout);
            let skip = skip.map(|s| &s[r0 * cout..(r0 + m) * cout]);
            self.row(&x[r0 * cin..(r0 + m) * cin], 0, 0, m, oband, skip);
        };
        if band >= n {
            run((0, &mut out));
        } else {
            out.par_chunks_mut(band * cout).enumerate().for_each(run);
        }
        out
    }

    /// A dense layer `cin -> cout` without bias whose weight `[out, in]` is `weight(out, in)`
    /// (attention's keys and values, packed per call).
    fn dense_from(cout: usize, cin: usize, weight: impl Fn(usize, usize) -> f32) -> Self {
        Self::packed([cout, cin, 1], None, 1, [0; 4], |co, ci, _| weight(co, ci))
    }

    /// Output channel vectors `v0..v0 + V` of every pixel of output row `oy`, `R` pixels a tile.
    #[inline(always)]
    fn columns<const R: usize, const V: usize>(
        &self,
        p: &[f32],
        rs: usize,
        oy: usize,
        ow: usize,
        v0: usize,
        orow: &mut [f32],
        skip: Option<&[f32]>,
    ) {
        let mut ox = 0;
        while ox + R <= ow {
            let acc = self.tile::<R, V>(p, rs, oy, ox, v0);
            self.store(&acc, ox, v0, orow, skip);
            ox += R;
        }
        while ox + 4 <= ow {
            let acc = self.tile::<4, V>(p, rs, oy, ox, v0);
            self.store(&acc, ox, v0, orow, skip);
            ox += 4;
        }
        while ox + 2 <= ow {
            let acc = self.tile::<2, V>(p, rs, oy, ox, v0);
            self.store(&acc, ox, v0, orow, skip);
            ox += 2;
        }
        while ox < ow {
            let acc = self.tile::<1, V>(p, rs, oy, ox, v0);
            self.store(&acc, ox, v0, orow, skip);
            ox += 1;
        }
    }

    /// The register tile: `R` output pixels from `ox0` x `V` vectors of output channels.
    #[inline(always)]
    fn tile<const R: usize, const V: usize>(
        &self,
        p: &[f32],
        rs: usize,
        oy: usize,
        ox0: usize,
        v0: usize,
    ) -> [[f32x16; V]; R] {
        let (k, s, cin, nv) = (self.k, self.stride, self.cin, self.nv);
        let bias = &self.bias[v0..v0 + V];
        let mut acc = [[f32x16::ZERO; V]; R];
        for row in acc.iter_mut() {
            row.copy_from_slice(bias);
        }
        for ky in 0..k {
            let base = (oy * s + ky) * rs;
            for kx in 0..k {
                let tap = ky * k + kx;
                let taps = &self.w[tap * cin * nv..(tap + 1) * cin * nv];
                let ins: [&[f32]; R] = std::array::from_fn(|r| {
                    let o = base + ((ox0 + r) * s + kx) * cin;
                    &p[o..o + cin]
                });
                for (ci, wrow) in taps.chunks_exact(nv).enumerate() {
                    let wv = &wrow[v0..v0 + V];
                    for r in 0..R {
                        let a = f32x16::splat(ins[r][ci]);
                        for v in 0..V {
                            acc[r][v] = a.mul_add(wv[v], acc[r][v]);
                        }
                    }
                }
            }
        }
        acc
    }

    #[inline(always)]
    fn store<const R: usize, const V: usize>(
        &self,
        acc: &[[f32x16; V]; R],
        ox0: usize,
        v0: usize,
        orow: &mut [f32],
        skip: Option<&[f32]>,
    ) {
        let cout = self.cout;
        for (r, vecs) in acc.iter().enumerate() {
            let base = (ox0 + r) * cout;
            for (v, vec) in vecs.iter().enumerate() {
                let c0 = (v0 + v) * LANES;
                let n = LANES.min(cout - c0);
                if n == LANES {
                    // a whole vector: a fixed-size store, not a call to memmove
                    let lanes = match skip {
                        Some(sk) => {
                            let mut s = [0.0f32; LANES];
                            s.copy_from_slice(&sk[base + c0..][..LANES]);
                            (*vec + f32x16::new(s)).to_array()
                        }
                        None => vec.to_array(),
                    };
                    orow[base + c0..][..LANES].copy_from_slice(&lanes);
                    continue;
                }
                let lanes = vec.to_array();
                let dst = &mut orow[base + c0..base + c0 + n];
                match skip {
                    Some(sk) => {
                        for ((d, l), s) in dst.iter_mut().zip(&lanes).zip(&sk[base + c0..base + c0 + n]) {
                            *d = l + s;
                        }
                    }
                    None => dst.copy_from_slice(&lanes[..n]),
                }
            }
        }
    }

    /// The inverse of [`Self::store`] without a skip: output rows `ox0..ox0 + R`, vectors
    /// `v0..v0 + V` of `orow` as accumulators (lanes past `cout` zero).
    #[inline(always)]
    pub(crate) fn load<const R: usize, const V: usize>(&self, ox0: usize, v0: usize, orow: &[f32]) -> [[f32x16; V]; R] {
        let mut acc = [[f32x16::ZERO; V]; R];
        for (r, vecs) in acc.iter_mut().enumerate() {
            let base = (ox0 + r) * self.cout;
            for (v, vec) in vecs.iter_mut().enumerate() {
                let c0 = (v0 + v) * LANES;
                let n = LANES.min(self.cout - c0);
                let mut lanes = [0.0f32; LANES];
                lanes[..n].copy_from_slice(&orow[base + c0..base + c0 + n]);
                *vec = f32x16::new(lanes);
            }
        }
        acc
    }
}

/// A convolution's weights on the host (`[cout, cin, k, k]`), its `[cout, cin, k]` and bias.
#[allow(clippy::type_complexity)]
fn conv_host(conv: &Conv2d) -> Result<(Vec<f32>, [usize; 3], Option<Vec<f32>>), ModelError> {
    let weight = conv.weight.val();
    let [cout, cin, kh, kw] = weight.dims();
    if kh != kw {
        return Err(ModelError::shape("a convolution for the CPU kernels", "a square kernel", format!("{kh}x{kw}")));
    }
    let bias = conv.bias.as_ref().map(|b| to_host(b.val())).transpose()?;
    Ok((to_host(weight)?, [cout, cin, kh], bias))
}

/// `dst = silu(src * scale + shift)`, element-wise.
fn norm_silu(src: &[f32], scale: &[f32], shift: &[f32], dst: &mut [f32]) {
    let full = src.len() / LANES * LANES;
    let load = |s: &[f32]| {
        let mut a = [0.0f32; LANES];
        a.copy_from_slice(s);
        f32x16::new(a)
    };
    for i in (0..full).step_by(LANES) {
        let v = load(&src[i..i + LANES]).mul_add(load(&scale[i..i + LANES]), load(&shift[i..i + LANES]));
        let y = v / (f32x16::ONE + (-v).exp());
        dst[i..i + LANES].copy_from_slice(&y.to_array());
    }
    for i in full..src.len() {
        let v = src[i] * scale[i] + shift[i];
        dst[i] = v / (1.0 + (-v).exp());
    }
}

/// Per channel of the pixels in `values` (`c` values each): the sum and the sum of squares (f64);
/// with `centre` (per group of `c / centre.len()` channels) the sum of squared deviations from it
/// in the second slot.
fn channel_sums(values: &[f32], c: usize, centre: Option<&[f64]>) -> Vec<[f64; 2]> {
    let mut s = vec![[0.0f64; 2]; c];
    let cg = centre.map_or(1, |m| (c / m.len().max(1)).max(1));
    for px in values.chunks_exact(c.max(1)) {
        for (ch, (acc, v)) in s.iter_mut().zip(px).enumerate() {
            let v = *v as f64;
            let d = centre.map_or(v, |m| v - m[(ch / cg).min(m.len() - 1)]);
            acc[0] += v;
            acc[1] += d * d;
        }
    }
    s
}

/// Per-channel sums of rows, added in row order (so they do not depend on how rows were split
/// between threads).
fn add_rows(rows: impl Iterator<Item = Vec<[f64; 2]>>, c: usize) -> Vec<[f64; 2]> {
    let mut total = vec![[0.0f64; 2]; c];
    for row in rows {
        for (t, r) in total.iter_mut().zip(row) {
            t[0] += r[0];
            t[1] += r[1];
        }
    }
    total
}

/// A GroupNorm's parameters.
#[derive(Debug)]
struct NormW {
    groups: usize,
    eps: f64,
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl NormW {
    fn new(norm: &Norm) -> Result<Self, ModelError> {
        Ok(Self {
            groups: norm.groups(),
            eps: norm.eps(),
            weight: to_host(norm.weight.val())?,
            bias: to_host(norm.bias.val())?,
        })
    }

    /// The normalisation of `x` as per-channel `(scale, shift)`: statistics per group over all
    /// pixels (biased variance, as burn's and PyTorch's GroupNorm), in f64.
    fn affine(&self, x: &Act) -> (Vec<f32>, Vec<f32>) {
        let c = x.c;
        let g = self.groups.clamp(1, c.max(1));
        let cg = (c / g).max(1);
        let count = (x.h * x.w * cg) as f64;
        let per_group = |sums: Vec<f64>| -> Vec<f64> {
            (0..g).map(|gi| sums[gi * cg..((gi + 1) * cg).min(c)].iter().sum::<f64>() / count.max(1.0)).collect()
        };
        let (mean, var) = match &x.sums {
            // one pass in f64 (sum and sum of squares, kept by the convolution that made `x`)
            Some(sums) if sums.len() == c => {
                let mean = per_group(sums.iter().map(|s| s[0]).collect());
                let squares = per_group(sums.iter().map(|s| s[1]).collect());
                let var = squares.iter().zip(&mean).map(|(q, m)| (q - m * m).max(0.0)).collect();
                (mean, var)
            }
            // two passes in f64, in pixel order
            _ => {
                let mean = per_group(channel_sums(&x.data, c, None).iter().map(|s| s[0]).collect());
                let var = per_group(channel_sums(&x.data, c, Some(&mean)).iter().map(|s| s[1]).collect());
                (mean, var)
            }
        };
        let (mut scale, mut shift) = (vec![0.0f32; c], vec![0.0f32; c]);
        for ch in 0..c {
            let gi = (ch / cg).min(g - 1);
            let inv = 1.0 / (var[gi] + self.eps).sqrt();
            let sc = self.weight[ch] as f64 * inv;
            scale[ch] = sc as f32;
            shift[ch] = (self.bias[ch] as f64 - mean[gi] * sc) as f32;
        }
        (scale, shift)
    }
}

#[derive(Debug)]
struct ResW {
    norm1: NormW,
    conv1: ConvW,
    norm2: NormW,
    conv2: ConvW,
    shortcut: Option<ConvW>,
}

impl ResW {
    fn new(b: &ResnetBlock) -> Result<Self, ModelError> {
        Ok(Self {
            norm1: NormW::new(&b.norm1)?,
            conv1: ConvW::same(&b.conv1)?,
            norm2: NormW::new(&b.norm2)?,
            conv2: ConvW::same(&b.conv2)?,
            shortcut: b.nin_shortcut.as_ref().map(ConvW::same).transpose()?,
        })
    }

    fn run(&self, x: &Act) -> Act {
        let h = self.conv1.after_norm(&self.norm1, x, None);
        match &self.shortcut {
            Some(proj) => self.conv2.after_norm(&self.norm2, &h, Some(&proj.run_with(x, Pre::Copy, None, false))),
            None => self.conv2.after_norm(&self.norm2, &h, Some(x)),
        }
    }
}

impl ConvW {
    /// `norm` + SiLU, then this convolution (+ `skip`).
    fn after_norm(&self, norm: &NormW, x: &Act, skip: Option<&Act>) -> Act {
        let (scale, shift) = norm.affine(x);
        self.run(x, Pre::NormSilu(&scale, &shift), skip)
    }
}

/// One level: residual blocks, then the resampling convolution (stride 2 down, or x2 up).
#[derive(Debug)]
struct Level {
    blocks: Vec<ResW>,
    resample: Option<ConvW>,
}

impl Level {
    /// The blocks, then the resampling convolution after `pre` (a copy down, x2 up).
    fn run(&self, x: Act, pre: Pre<'_>) -> Act {
        let a = self.blocks.iter().fold(x, |a, b| b.run(&a));
        match &self.resample {
            Some(conv) => conv.run(&a, pre, None),
            None => a,
        }
    }
}

fn mid(m: &Mid) -> Result<[ResW; 2], ModelError> {
    Ok([ResW::new(&m.block_1)?, ResW::new(&m.block_2)?])
}

/// The encoder and decoder of a [`VqModel`] without attention, for the CPU kernels.
#[derive(Debug)]
pub struct NhwcNet {
    /// The mask fusion (1x1), where it is not folded into the stem.
    mask_in: Option<ConvW>,
    input_channels: usize,
    stem: ConvW,
    down: Vec<Level>,
    enc_mid: [ResW; 2],
    enc_norm_out: NormW,
    enc_conv_out: ConvW,
    quant_conv: ConvW,
    /// The code head, negated: its output is the sampler's "distances" (lower is likelier).
    neg_head: Option<ConvW>,
    /// `[n_embed][embed_dim]`.
    codebook: Vec<f32>,
    embed_dim: usize,
    post_quant: ConvW,
    dec_conv_in: ConvW,
    dec_mid: [ResW; 2],
    /// In the order they run (lowest resolution first).
    up: Vec<Level>,
    dec_norm_out: NormW,
    dec_conv_out: ConvW,
    patch: usize,
    /// The scene-wide context, where the model has one.
    context: Option<context::CpuContext>,
}

impl NhwcNet {
    /// The model's weights in the kernels' layout; `None` for a model with attention (not
    /// covered: it keeps burn's path).
    pub fn new(model: &VqModel, config: &ModelConfig) -> Result<Option<Self>, ModelError> {
        let enc = &model.encoder;
        let dec = &model.decoder;
        let attention = enc.down.iter().any(|l| !l.attn.is_empty())
            || dec.up.iter().any(|l| !l.attn.is_empty())
            || enc.mid.attn_1.is_some()
            || dec.mid.attn_1.is_some();
        if attention {
            return Ok(None);
        }
        let p = config.patch_size;
        // a patch stem has no padding: the mask fusion folds into it (one pass over the input)
        let (mask_in, stem) = if p > 1 {
            (None, ConvW::after_pointwise(&enc.conv_in, &model.conv_in, p)?)
        } else {
            (Some(ConvW::same(&model.conv_in)?), ConvW::same(&enc.conv_in)?)
        };
        let down = enc
            .down
            .iter()
            .map(|l| {
                Ok(Level {
                    blocks: l.block.iter().map(ResW::new).collect::<Result<_, ModelError>>()?,
                    // taming's downsampling: pad right and bottom by one, 3x3 stride 2
                    resample: l.downsample.as_ref().map(|d| ConvW::new(&d.conv, 2, [0, 0, 1, 1])).transpose()?,
                })
            })
            .collect::<Result<Vec<_>, ModelError>>()?;
        let up = dec
            .up
            .iter()
            .rev()
            .map(|l| {
                Ok(Level {
                    blocks: l.block.iter().map(ResW::new).collect::<Result<_, ModelError>>()?,
                    resample: l.upsample.as_ref().map(|u| ConvW::same(&u.conv)).transpose()?,
                })
            })
            .collect::<Result<Vec<_>, ModelError>>()?;
        Ok(Some(Self {
            mask_in,
            input_channels: config.input_channels(),
            stem,
            down,
            enc_mid: mid(&enc.mid)?,
            enc_norm_out: NormW::new(&enc.norm_out)?,
            enc_conv_out: ConvW::same(&enc.conv_out)?,
            quant_conv: ConvW::same(&model.quant_conv)?,
            neg_head: model.code_head.as_ref().map(|h| ConvW::same(h).map(ConvW::negated)).transpose()?,
            codebook: to_host(model.quantize.embedding.weight.val())?,
            embed_dim: config.embed_dim,
            post_quant: ConvW::same(&model.post_quant_conv)?,
            dec_conv_in: ConvW::same(&dec.conv_in)?,
            dec_mid: mid(&dec.mid)?,
            up,
            dec_norm_out: NormW::new(&dec.norm_out)?,
            dec_conv_out: ConvW::same(&dec.conv_out)?,
            patch: p,
            context: match (&model.context, &config.context) {
                (Some(c), Some(cfg)) => Some(context::CpuContext::new(c, cfg.heads)?),
                _ => None,
            },
        }))
    }

    /// Mask fusion + encoder ([`VqModel::features`]) of one packed image `x` (NCHW planes).
    pub fn features(&self, x: &[f32], c: usize, h: usize, w: usize) -> Result<Act, ModelError> {
        if c != self.input_channels || x.len() != c * h * w {
            return Err(ModelError::shape(
                "an input to the CPU kernels",
                format!("{} planes of {h}x{w}", self.input_channels),
                format!("{c} planes, {} values", x.len()),
            ));
        }
        let x = Act::from_nchw(x, c, h, w);
        let mut a = match &self.mask_in {
            Some(m) => self.stem.run(&m.run_with(&x, Pre::Copy, None, false), Pre::Copy, None),
            None => self.stem.run(&x, Pre::Copy, None),
        };
        for level in &self.down {
            a = level.run(a, Pre::Copy);
        }
        let a = self.enc_mid.iter().fold(a, |a, b| b.run(&a));
        Ok(self.enc_conv_out.after_norm(&self.enc_norm_out, &a, None))
    }

    /// The code head's logits of [`Self::features`], negated (`[h * w, n_embed]` row-major as
    /// the activation's data: lower is likelier); `None` without a head.
    pub fn neg_logits(&self, features: &Act) -> Option<Act> {
        self.neg_head.as_ref().map(|h| h.run_with(features, Pre::Copy, None, false))
    }

    /// The context's residual code logits (`[h * w, n_embed]`) of one window of `h x w` cells:
    /// their encoder features (`[h * w, z]`, as [`Self::features`] rows) and states, the
    /// revealed cells' codes read from the model's codebook ([`crate::context::CodeContext`]).
    /// `None` for a model without a context.
    pub fn context_residual(
        &self,
        features: &[f32],
        states: &[CellState],
        [h, w]: [usize; 2],
    ) -> Option<Result<Vec<f32>, ModelError>> {
        self.context.as_ref().map(|c| c.residual(features, states, &self.codebook, [h, w]))
    }

    /// `quant_conv` of [`Self::features`]: the pre-quantization latent ([`VqModel::encode`]).
    pub fn latent(&self, features: &Act) -> Act {
        self.quant_conv.run_with(features, Pre::Copy, None, false)
    }

    /// Decodes one code per latent cell (`[h][w]` row-major) into packed planes `4 x H x W`
    /// (`H = h * f`), as [`VqModel::decode`] of the codebook rows.
    pub fn decode_codes(&self, codes: &[u32], h: usize, w: usize) -> Result<Vec<f32>, ModelError> {
        let d = self.embed_dim;
        let n = self.codebook.len() / d.max(1);
        if codes.len() != h * w {
            return Err(ModelError::shape(
                "codes to decode",
                format!("{} codes for {h}x{w} cells", h * w),
                codes.len(),
            ));
        }
        let mut data = Vec::with_capacity(h * w * d);
        for &c in codes {
            let c = c as usize;
            if c >= n {
                return Err(ModelError::shape("a code to decode", format!("an index below {n}"), c));
            }
            data.extend_from_slice(&self.codebook[c * d..(c + 1) * d]);
        }
        let z = Act { h, w, c: d, data, sums: None };
        let a = self.dec_conv_in.run(&self.post_quant.run(&z, Pre::Copy, None), Pre::Copy, None);
        let mut a = self.dec_mid.iter().fold(a, |a, b| b.run(&a));
        for level in &self.up {
            a = level.run(a, Pre::Up2);
        }
        let out = self.dec_conv_out.after_norm(&self.dec_norm_out, &a, None);
        Ok(pixel_shuffle_planes(&out, self.patch))
    }
}

/// Depth to space in PyTorch's channel order (`c r r`), NHWC in, planes (`c x H r x W r`) out.
fn pixel_shuffle_planes(a: &Act, r: usize) -> Vec<f32> {
    let c = a.c / (r * r);
    let (oh, ow) = (a.h * r, a.w * r);
    let mut out = vec![0.0f32; c * oh * ow];
    for y in 0..a.h {
        for x in 0..a.w {
            let px = &a.data[(y * a.w + x) * a.c..(y * a.w + x + 1) * a.c];
            for ch in 0..c {
                for i in 0..r {
                    for j in 0..r {
                        out[(ch * oh + y * r + i) * ow + x * r + j] = px[(ch * r + i) * r + j];
                    }
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Distribution, Tensor};

    fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
    }

    fn scale(a: &[f32]) -> f32 {
        a.iter().map(|x| x.abs()).fold(0.0, f32::max).max(1e-6)
    }

    /// `module` with every parameter moved off its initial value by up to `spread(name)` (a
    /// deterministic hash per value), so no term of a pass is an identity or zero.
    pub(super) fn perturbed<M: burn::module::Module>(module: M, spread: impl Fn(&str) -> f32) -> M {
        let mut tensors = crate::params::named_tensors(&module);
        for (i, (name, t)) in tensors.iter_mut().enumerate() {
            let spread = spread(name);
            for (j, v) in t.values.iter_mut().enumerate() {
                let u =
                    (((i * 7919 + j) as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 40) as f32 / (1u64 << 24) as f32;
                *v += spread * (2.0 * u - 1.0);
            }
        }
        crate::params::load_named(module, &tensors, false, false).expect("perturbed weights")
    }

    /// A model with every weight moved (norms' scales and shifts too, and a codebook spread like
    /// a trained one's).
    fn model(config: &ModelConfig) -> VqModel {
        let m = VqModel::new(config, 3, &crate::default_device()).expect("model");
        perturbed(m, |name| if name.contains("embedding") { 1.0 } else { 0.2 })
    }

    fn configs() -> Vec<ModelConfig> {
        let mut tiny = ModelConfig::tiny();
        tiny.mid_attn = false;
        tiny.code_head = true;
        let mut compact = ModelConfig::compact();
        compact.code_head = true;
        compact.ray_channels = true;
        // a 3x3 stem (padded): the mask fusion stays its own pass
        let plain_stem = ModelConfig { patch_size: 1, resolution: 16, ..tiny.clone() };
        vec![tiny, plain_stem, ModelConfig::compact(), compact]
    }

    #[test]
    fn features_logits_and_latent_equal_burns() {
        let device = crate::default_device();
        for cfg in configs() {
            let m = model(&cfg);
            let net = NhwcNet::new(&m, &cfg).expect("weights").expect("no attention");
            let (c, h, w) = (cfg.input_channels(), 64, 48);
            let x = Tensor::<4>::random([1, c, h, w], Distribution::Uniform(-1.0, 1.0), &device);
            let host = to_host(x.clone()).expect("host");
            let feats = net.features(&host, c, h, w).expect("features");
            let burn_feats = to_host(m.features(x.clone()).permute([0, 2, 3, 1])).expect("host");
            let d = max_abs_diff(&feats.data, &burn_feats);
            assert!(d <= 1e-4 * scale(&burn_feats), "{}: features differ by {d}", cfg.name);
            let z = net.latent(&feats);
            let burn_z = to_host(m.encode(x.clone()).permute([0, 2, 3, 1])).expect("host");
            assert!(max_abs_diff(&z.data, &burn_z) <= 1e-4 * scale(&burn_z), "{}: latent", cfg.name);
            match (net.neg_logits(&feats), m.code_logits(x)) {
                (Some(l), Some(bl)) => {
                    let bl = to_host(bl.permute([0, 2, 3, 1]).neg()).expect("host");
                    assert!(max_abs_diff(&l.data, &bl) <= 1e-4 * scale(&bl), "{}: logits", cfg.name);
                }
                (None, None) => {}
                _ => panic!("{}: a head on one side only", cfg.name),
            }
        }
    }

    #[test]
    fn decoding_codes_equals_burns() {
        let device = crate::default_device();
        for cfg in configs() {
            let m = model(&cfg);
            let net = NhwcNet::new(&m, &cfg).expect("weights").expect("no attention");
            let (h, w) = (5, 7); // odd, to run the kernels' tails
            let codes: Vec<u32> = (0..h * w).map(|i| ((i * 37 + 5) % cfg.n_embed) as u32).collect();
            let ours = net.decode_codes(&codes, h, w).expect("decode");
            let rows = m.quantize.lookup(&codes, &device);
            let z_q = rows.reshape([1, h, w, cfg.embed_dim]).permute([0, 3, 1, 2]);
            let theirs = to_host(m.decode(z_q)).expect("host");
            let d = max_abs_diff(&ours, &theirs);
            assert!(d <= 1e-4 * scale(&theirs), "{}: decoded planes differ by {d}", cfg.name);
        }
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let mut cfg = ModelConfig::compact();
        cfg.code_head = true;
        let net = NhwcNet::new(&model(&cfg), &cfg).expect("weights").expect("no attention");
        let (c, h, w) = (cfg.input_channels(), 64, 40);
        let x: Vec<f32> = (0..c * h * w).map(|i| ((i * 7919) % 1000) as f32 / 500.0 - 1.0).collect();
        let codes: Vec<u32> = (0..8 * 5).map(|i| (i * 37 % cfg.n_embed) as u32).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
            pool.install(|| {
                let f = net.features(&x, c, h, w).expect("features");
                (net.neg_logits(&f).expect("head").data, net.decode_codes(&codes, 8, 5).expect("decode"))
            })
        };
        let one = run(1);
        for threads in [2, 3, 5] {
            assert!(run(threads) == one, "{threads} threads differ from one");
        }
    }

    #[test]
    fn bad_inputs_are_errors() {
        let mut cfg = ModelConfig::tiny();
        cfg.mid_attn = false;
        let net = NhwcNet::new(&model(&cfg), &cfg).expect("weights").expect("no attention");
        assert!(net.features(&[0.0; 10], 5, 2, 2).is_err());
        assert!(net.decode_codes(&[0, 1], 2, 2).is_err());
        assert!(net.decode_codes(&[cfg.n_embed as u32; 4], 2, 2).is_err());
    }

    #[test]
    fn a_model_with_attention_keeps_burns_path() {
        let cfg = ModelConfig::tiny(); // attention at the bottleneck
        assert!(cfg.mid_attn);
        assert!(NhwcNet::new(&model(&cfg), &cfg).expect("weights").is_none());
    }

    #[test]
    fn layouts_round_trip() {
        let v: Vec<f32> = (0..2 * 3 * 4).map(|i| i as f32).collect();
        let a = Act::from_nchw(&v, 2, 3, 4);
        // pixel (y, x), channel ch holds plane ch's value at (y, x)
        for (p, px) in a.data.chunks_exact(2).enumerate() {
            assert_eq!(px, [v[p], v[12 + p]], "pixel {p}");
        }
        // pixel shuffle: channel (c, i, j) of pixel (y, x) lands at (y r + i, x r + j)
        let a = Act { h: 1, w: 1, c: 4, data: vec![1.0, 2.0, 3.0, 4.0], sums: None };
        assert_eq!(pixel_shuffle_planes(&a, 2), vec![1.0, 2.0, 3.0, 4.0]);
        let a = Act { h: 1, w: 2, c: 4, data: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0], sums: None };
        assert_eq!(pixel_shuffle_planes(&a, 2), vec![1.0, 2.0, 5.0, 6.0, 3.0, 4.0, 7.0, 8.0]);
    }
}
