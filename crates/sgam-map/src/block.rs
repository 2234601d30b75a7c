//! Dense 8^3 voxel blocks and the integer grid they live on.

use glam::IVec3;
use wide::{bytemuck::cast, f32x8, i32x8};

/// Voxels per block edge.
pub const BLOCK_SIZE: i32 = 8;
/// Voxels per block.
pub const BLOCK_VOXELS: usize = 512;

/// One voxel: truncated signed distance (normalised to `[-1, 1]` by the truncation), the
/// accumulated weight (0 = never observed) and the averaged sRGB colour in `[0, 1]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Voxel {
    /// Normalised truncated signed distance: positive in front of the surface (free space),
    /// negative behind it; `1` far in front.
    pub tsdf: f32,
    /// Number of observations averaged (possibly capped); `0` = unobserved.
    pub weight: f32,
    /// Averaged colour, sRGB `[0, 1]`.
    pub colour: [f32; 3],
}

impl Voxel {
    /// An unobserved voxel.
    pub const EMPTY: Voxel = Voxel { tsdf: 1.0, weight: 0.0, colour: [0.0; 3] };
}

/// Voxel rows (of 8 along x) per block.
pub(crate) const ROWS: usize = (BLOCK_SIZE * BLOCK_SIZE) as usize;
const N: usize = BLOCK_SIZE as usize;

/// A dense block of `8 x 8 x 8` voxels; voxel `(x, y, z)` (local, each in `0..8`) is at index
/// `x + 8 y + 64 z`. Block key `k` covers global voxels `8 k .. 8 k + 7` on each axis.
///
/// Stored as planes (tsdf, weight, and one per colour channel), each as 64 rows of 8 voxels
/// along x: the integration updates a row with 8-wide vector operations, and meshing reads only
/// the tsdf and weight planes.
#[derive(Debug, Clone, PartialEq)]
pub struct Block {
    pub(crate) planes: Box<Planes>,
}

/// The voxel planes of a [`Block`]; row `y + 8 z`, lane `x`.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Planes {
    pub tsdf: [[f32; N]; ROWS],
    pub weight: [[f32; N]; ROWS],
    pub colour: [[[f32; N]; ROWS]; 3],
}

impl Default for Block {
    fn default() -> Self {
        Self {
            planes: Box::new(Planes {
                tsdf: [[Voxel::EMPTY.tsdf; N]; ROWS],
                weight: [[Voxel::EMPTY.weight; N]; ROWS],
                colour: [[[0.0; N]; ROWS]; 3],
            }),
        }
    }
}

impl Block {
    /// Voxel `i` ([`local_index`]).
    #[inline]
    pub fn voxel(&self, i: usize) -> Voxel {
        let (r, x) = (i / N, i % N);
        let p = &self.planes;
        Voxel {
            tsdf: p.tsdf[r][x],
            weight: p.weight[r][x],
            colour: [p.colour[0][r][x], p.colour[1][r][x], p.colour[2][r][x]],
        }
    }

    /// Overwrites voxel `i` ([`local_index`]).
    #[inline]
    pub fn set_voxel(&mut self, i: usize, v: Voxel) {
        let (r, x) = (i / N, i % N);
        let p = &mut self.planes;
        p.tsdf[r][x] = v.tsdf;
        p.weight[r][x] = v.weight;
        for ch in 0..3 {
            p.colour[ch][r][x] = v.colour[ch];
        }
    }

    /// All voxels in index order ([`local_index`]).
    pub fn voxels(&self) -> impl Iterator<Item = Voxel> + '_ {
        (0..BLOCK_VOXELS).map(|i| self.voxel(i))
    }
}

/// Index of local voxel `(x, y, z)` inside a block.
#[inline]
pub fn local_index(x: i32, y: i32, z: i32) -> usize {
    (x + BLOCK_SIZE * (y + BLOCK_SIZE * z)) as usize
}

/// The block key holding global voxel `g`.
#[inline]
pub fn block_of_voxel(g: IVec3) -> IVec3 {
    IVec3::new(g.x.div_euclid(BLOCK_SIZE), g.y.div_euclid(BLOCK_SIZE), g.z.div_euclid(BLOCK_SIZE))
}

/// Local coordinates of global voxel `g` inside its block.
#[inline]
pub fn voxel_in_block(g: IVec3) -> IVec3 {
    IVec3::new(g.x.rem_euclid(BLOCK_SIZE), g.y.rem_euclid(BLOCK_SIZE), g.z.rem_euclid(BLOCK_SIZE))
}

/// `floor(x)` as `i32` without a libm call (the baseline x86-64 target has no `roundss`);
/// saturates outside the `i32` range, NaN gives 0.
#[inline(always)]
pub(crate) fn floor_i32(x: f32) -> i32 {
    let i = x as i32;
    // saturating: below `i32::MIN` (e.g. -inf) `i` is already `i32::MIN`
    i.saturating_sub(((i as f32) > x) as i32)
}

/// [`floor_i32`] of 8 lanes, for `|x| < 2^31` (truncation, minus one where it rounded up).
#[inline(always)]
pub(crate) fn floor_i32x8(x: f32x8) -> i32x8 {
    let i = x.fast_trunc_int();
    i + cast::<f32x8, i32x8>(i.round_float().simd_gt(x))
}

/// Component-wise [`floor_i32`].
#[inline(always)]
pub(crate) fn floor_ivec3(v: glam::Vec3) -> IVec3 {
    IVec3::new(floor_i32(v.x), floor_i32(v.y), floor_i32(v.z))
}
