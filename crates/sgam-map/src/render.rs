//! Guidance rendering: z-buffered rasterization of the block meshes, and a TSDF ray-cast.

use glam::{IVec3, Vec3};
use rayon::prelude::*;
use sgam_core::{Camera, Image, Rigid3, Vec2};
use wide::f32x8;

use crate::block::{block_of_voxel, floor_i32x8, floor_ivec3, local_index, voxel_in_block, Block, Voxel};
use crate::TsdfMap;

/// A rendered view of the map at a pinhole camera.
#[derive(Debug, Clone, PartialEq)]
pub struct Rendered {
    /// Planar depth in metres (camera z); `0` where nothing was hit.
    pub depth_m: Image<f32>,
    /// sRGB colour in `[0, 1]` interpolated from the map; black where nothing was hit.
    pub colour: Image<[f32; 3]>,
    /// Row-major `[H, W]`; true where a surface was hit.
    pub covered: Vec<bool>,
    /// Row-major `[H, W]`; true where the nearest surface was seen from its back (inside / behind
    /// an observed surface). Rasterizer only; always false for the ray-cast.
    pub back_facing: Vec<bool>,
    /// Blocks whose meshes (rasterizer) or voxels (ray-cast, counted once per ray) were used;
    /// bounded by the frustum, not the map size.
    pub blocks_visited: usize,
}

impl Rendered {
    /// Takes `other`'s pixels where it hit a surface nearer than this rendering did (or where
    /// this one hit nothing): two parts of a map rendered apart, then merged, give what the
    /// whole map renders (up to ties between equal depths). Errors on another image size.
    pub fn merge_nearer(&mut self, other: &Rendered) -> Result<(), crate::MapError> {
        if (self.depth_m.width, self.depth_m.height) != (other.depth_m.width, other.depth_m.height) {
            return Err(crate::MapError::InvalidContent(format!(
                "merging a {}x{} rendering into a {}x{} one",
                other.depth_m.width, other.depth_m.height, self.depth_m.width, self.depth_m.height
            )));
        }
        for i in 0..self.covered.len() {
            if other.covered[i] && (!self.covered[i] || other.depth_m.data[i] < self.depth_m.data[i]) {
                self.covered[i] = true;
                self.depth_m.data[i] = other.depth_m.data[i];
                self.colour.data[i] = other.colour.data[i];
                self.back_facing[i] = other.back_facing[i];
            }
        }
        self.blocks_visited += other.blocks_visited;
        Ok(())
    }

    fn empty(width: u32, height: u32) -> Self {
        let n = width as usize * height as usize;
        Self {
            depth_m: Image::filled(width, height, 0.0),
            colour: Image::filled(width, height, [0.0; 3]),
            covered: vec![false; n],
            back_facing: vec![false; n],
            blocks_visited: 0,
        }
    }
}

/// A view frustum as inward-facing planes `n . p + d >= 0` in world coordinates.
#[derive(Debug, Clone, Copy)]
struct Frustum {
    planes: [(Vec3, f32); 6],
}

impl Frustum {
    fn new(camera: &Camera, near_m: f32, far_m: f32) -> Self {
        let k = camera.intrinsics;
        let r = camera.world_from_camera.rotation;
        let t = camera.world_from_camera.translation;
        let left = (-0.5 - k.cx) / k.fx;
        let right = (k.width as f32 - 0.5 - k.cx) / k.fx;
        let top = (-0.5 - k.cy) / k.fy;
        let bottom = (k.height as f32 - 0.5 - k.cy) / k.fy;
        let side = |n_c: Vec3| {
            let n = r * n_c;
            (n, -n.dot(t))
        };
        let fwd = r * Vec3::Z;
        Self {
            planes: [
                side(Vec3::new(1.0, 0.0, -left)),
                side(Vec3::new(-1.0, 0.0, right)),
                side(Vec3::new(0.0, 1.0, -top)),
                side(Vec3::new(0.0, -1.0, bottom)),
                (fwd, -fwd.dot(t) - near_m),
                (-fwd, fwd.dot(t) + far_m),
            ],
        }
    }

    /// Conservative: false only when the box is entirely outside one plane.
    fn intersects_aabb(&self, lo: Vec3, hi: Vec3) -> bool {
        self.planes.iter().all(|(n, d)| {
            let p = Vec3::select(n.cmpge(Vec3::ZERO), hi, lo);
            n.dot(p) + d >= 0.0
        })
    }
}

/// A triangle in screen space: pixel coordinates, `1/z`, vertex colours, and facing.
#[derive(Debug, Clone, Copy)]
struct ScreenTri {
    p: [Vec2; 3],
    inv_z: [f32; 3],
    col: [Vec3; 3],
    back: bool,
}

/// A mesh vertex seen by the camera: camera-space position, pixel position, and the pixel
/// centres around it (`ceil` and `floor` of the pixel coordinates).
#[derive(Debug, Clone, Copy)]
struct ProjVertex {
    c: Vec3,
    /// `1 / c.z`
    inv_z: f32,
    s: Vec2,
    ceil: [i32; 2],
    floor: [i32; 2],
}

/// Projects mesh vertices into `out` (cleared first), 8 at a time (`wide`): camera-space
/// position, `1/z`, pixel position and the pixel-centre range a triangle's bounding box is built
/// from (clamped to +-1e9 first: vertices at or behind the camera plane project to infinities
/// or NaN; their triangles are dropped by the near test).
fn project_vertices(positions: &[Vec3], camera_from_world: &Rigid3, camera: &Camera, out: &mut Vec<ProjVertex>) {
    let k = camera.intrinsics;
    let (r, t) = (camera_from_world.rotation, camera_from_world.translation);
    let splat = f32x8::splat;
    let (lo, hi) = (splat(-1.0e9), splat(1.0e9));
    let floor = |x: f32x8| floor_i32x8(x).to_array();
    out.clear();
    out.reserve(positions.len());
    for chunk in positions.chunks(8) {
        let (mut x, mut y, mut z) = ([0.0f32; 8], [0.0f32; 8], [0.0f32; 8]);
        for (l, p) in chunk.iter().enumerate() {
            (x[l], y[l], z[l]) = (p.x, p.y, p.z);
        }
        let (x, y, z) = (f32x8::new(x), f32x8::new(y), f32x8::new(z));
        // rotation * p + translation, in glam's order of operations
        let row = |a: Vec3, b: f32| splat(a.x) * x + splat(a.y) * y + splat(a.z) * z + splat(b);
        let cx = row(Vec3::new(r.x_axis.x, r.y_axis.x, r.z_axis.x), t.x);
        let cy = row(Vec3::new(r.x_axis.y, r.y_axis.y, r.z_axis.y), t.y);
        let cz = row(Vec3::new(r.x_axis.z, r.y_axis.z, r.z_axis.z), t.z);
        let iz = splat(1.0) / cz;
        let sx = splat(k.fx) * cx * iz + splat(k.cx);
        let sy = splat(k.fy) * cy * iz + splat(k.cy);
        // NaN clamps to the lower bound (like `f32::max`)
        let (qx, qy) = (sx.max(lo).min(hi), sy.max(lo).min(hi));
        let (floor_x, floor_y) = (floor(qx), floor(qy));
        let (neg_ceil_x, neg_ceil_y) = (floor(-qx), floor(-qy));
        let [cx, cy, cz, iz, sx, sy] = [cx, cy, cz, iz, sx, sy].map(|v| v.to_array());
        out.extend((0..chunk.len()).map(|l| ProjVertex {
            c: Vec3::new(cx[l], cy[l], cz[l]),
            inv_z: iz[l],
            s: Vec2::new(sx[l], sy[l]),
            ceil: [-neg_ceil_x[l], -neg_ceil_y[l]],
            floor: [floor_x[l], floor_y[l]],
        }));
    }
}

/// A ray hit: planar depth (metres, 0 = none) and colour.
type Hit = (f32, [f32; 3]);

const EDGE_EPS: f32 = 1e-5;

impl TsdfMap {
    /// The ids of blocks whose AABB intersects the view frustum between `depth_min_m` and
    /// `depth_max_m`, ascending.
    fn blocks_in_frustum(&self, camera: &Camera, near: f32, far: f32) -> Vec<u32> {
        let frustum = Frustum::new(camera, near, far);
        let corners = camera.frustum_corners_world(near, far);
        let (lo, hi) = corners.iter().fold((corners[0], corners[0]), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
        self.blocks_where(lo, hi, |a, b| frustum.intersects_aabb(a, b))
    }

    /// Z-buffered rasterization of the map's block meshes at `camera`, after re-meshing the
    /// dirty blocks (with the map's weight threshold).
    ///
    /// Only blocks whose AABB intersects the frustum (`depth_min_m..depth_max_m`) are touched.
    /// Depth is perspective-correct (`1/z` interpolated in screen space); colour likewise.
    /// Pixel `(u, v)` is sampled at its centre. Triangles with any vertex nearer than
    /// `depth_min_m` are skipped (not clipped); hits beyond `depth_max_m` are dropped.
    ///
    /// Back faces are **not** culled: a surface seen from behind still occludes what lies
    /// beyond it (the TSDF says the space behind an observed surface is occupied), and the
    /// nearest hit wins either way; such pixels are flagged in [`Rendered::back_facing`].
    /// Blocks are split into contiguous chunks rasterized in parallel, each into its own
    /// z-buffer; the merge keeps the nearest hit and, on exact ties, the earlier chunk, so the
    /// result is deterministic whatever the number of threads.
    pub fn remesh_and_rasterize(&mut self, camera: &Camera) -> Rendered {
        self.update_mesh();
        self.rasterize(camera)
    }

    /// The rasterizer behind [`TsdfMap::remesh_and_rasterize`], on the block meshes as they are (no
    /// re-meshing).
    pub fn rasterize(&self, camera: &Camera) -> Rendered {
        self.rasterize_range(camera, self.config.depth_min_m, self.config.depth_max_m)
    }

    /// [`TsdfMap::rasterize`] with its own depth range instead of the map's (e.g. an overview
    /// of the whole map from farther away than the sensor range).
    pub fn rasterize_range(&self, camera: &Camera, near_m: f32, far_m: f32) -> Rendered {
        let k = camera.intrinsics;
        let w = k.width as usize;
        let mut out = Rendered::empty(k.width, k.height);
        let Some((buffers, visited)) = self.z_buffers::<true>(camera, near_m, far_m) else { return out };
        out.blocks_visited = visited;
        // Merge (nearest wins; on exact ties the earlier chunk) and resolve, in parallel over rows.
        let rows = w.max(1);
        out.depth_m
            .data
            .par_chunks_mut(rows)
            .zip(out.colour.data.par_chunks_mut(rows))
            .zip(out.covered.par_chunks_mut(rows))
            .zip(out.back_facing.par_chunks_mut(rows))
            .enumerate()
            .for_each(|(v, (((depth, colour), covered), back))| {
                for u in 0..depth.len() {
                    let i = v * w + u;
                    let best = nearest_buffer(&buffers, i);
                    if best.inv_z[i] > 0.0 {
                        depth[u] = 1.0 / best.inv_z[i];
                        colour[u] = best.colour[i];
                        covered[u] = true;
                        back[u] = best.back[i];
                    }
                }
            });
        out
    }

    /// Planar depth only (metres, `0` where nothing was hit) of [`TsdfMap::remesh_and_rasterize`]: what the
    /// generator's guidance needs. Re-meshes dirty blocks first, like `remesh_and_rasterize`; the
    /// depth is bit-identical to `remesh_and_rasterize(camera).depth_m`, without the colour and
    /// facing work.
    pub fn remesh_and_rasterize_depth(&mut self, camera: &Camera) -> Image<f32> {
        self.update_mesh();
        self.rasterize_depth(camera)
    }

    /// Planar depth only of [`TsdfMap::rasterize`] (no re-meshing).
    pub fn rasterize_depth(&self, camera: &Camera) -> Image<f32> {
        let k = camera.intrinsics;
        let w = k.width as usize;
        let mut out = Image::filled(k.width, k.height, 0.0f32);
        let Some((buffers, _)) = self.z_buffers::<false>(camera, self.config.depth_min_m, self.config.depth_max_m)
        else {
            return out;
        };
        out.data.par_chunks_mut(w.max(1)).enumerate().for_each(|(v, depth)| {
            for (u, d) in depth.iter_mut().enumerate() {
                let i = v * w + u;
                let iz = nearest_buffer(&buffers, i).inv_z[i];
                if iz > 0.0 {
                    *d = 1.0 / iz;
                }
            }
        });
        out
    }

    /// The per-chunk z-buffers of the blocks in the frustum (with colour and facing when
    /// `SHADE`), and the number of blocks rasterized; `None` when there is nothing to draw.
    ///
    /// Blocks are split into contiguous chunks, each rasterized into its own z-buffer; merging
    /// them with [`nearest_buffer`] (nearest hit, on exact ties the earlier chunk) gives the
    /// same result as one sequential pass in allocation order, whatever the number of threads.
    fn z_buffers<const SHADE: bool>(&self, camera: &Camera, near_m: f32, far_m: f32) -> Option<(Vec<ZBuffer>, usize)> {
        let k = camera.intrinsics;
        let (w, h) = (k.width as usize, k.height as usize);
        if !camera.world_from_camera.is_finite() {
            return None;
        }
        let (near, far) = (near_m.max(1e-4), far_m);
        let mut ids: Vec<u32> = self
            .blocks_in_frustum(camera, near, far)
            .into_iter()
            .filter(|&i| !self.meshes[i as usize].is_empty())
            .collect();
        // allocation order (= id order unless blocks were evicted and restored): exact depth
        // ties go to the same block either way
        ids.sort_unstable_by_key(|&i| self.order[i as usize]);
        let camera_from_world = camera.world_from_camera.inverse();
        // Contiguous chunks of about equal work (triangles + vertices), one per thread.
        let cost = |id: u32| {
            let m = &self.meshes[id as usize];
            m.triangles.len() + m.positions.len()
        };
        let total: usize = ids.iter().map(|&id| cost(id)).sum();
        let threads = rayon::current_num_threads().max(1);
        let mut chunks: Vec<&[u32]> = Vec::with_capacity(threads);
        let (mut start, mut acc) = (0usize, 0usize);
        for (i, &id) in ids.iter().enumerate() {
            acc += cost(id);
            if acc * threads >= total * (chunks.len() + 1) && chunks.len() + 1 < threads {
                chunks.push(&ids[start..=i]);
                start = i + 1;
            }
        }
        chunks.push(&ids[start..]);
        let buffers: Vec<ZBuffer> = chunks
            .into_par_iter()
            .map(|chunk| {
                let mut zb = ZBuffer::new(w, h, SHADE);
                let mut projected = Vec::new();
                for &id in chunk {
                    self.raster_block::<SHADE>(id, &camera_from_world, camera, near, far, &mut projected, &mut zb);
                }
                zb
            })
            .collect();
        (!buffers.is_empty()).then_some((buffers, ids.len()))
    }

    /// Rasterizes the mesh of block `id` into `zb` (colour and facing too when `SHADE`);
    /// `projected` is scratch space.
    fn raster_block<const SHADE: bool>(
        &self,
        id: u32,
        camera_from_world: &Rigid3,
        camera: &Camera,
        near: f32,
        far: f32,
        projected: &mut Vec<ProjVertex>,
        zb: &mut ZBuffer,
    ) {
        let m = &self.meshes[id as usize];
        let k = camera.intrinsics;
        // Vertex colours: cached, or computed from the voxels (re-meshing drops them).
        let computed;
        let colours: &[[f32; 3]] = if !SHADE || m.has_colours() {
            &m.colours
        } else {
            computed = self.vertex_colours(id);
            &computed
        };
        project_vertices(&m.positions, camera_from_world, camera, projected);
        let (w1, h1) = (k.width as i32 - 1, k.height as i32 - 1);
        for tri in &m.triangles {
            let [a, b, c] = tri.map(|i| &projected[i as usize]);
            if a.c.z < near || b.c.z < near || c.c.z < near {
                continue;
            }
            // Pixel centres inside the bounding box (none for most sub-pixel triangles).
            let x0 = a.ceil[0].min(b.ceil[0]).min(c.ceil[0]).max(0);
            let x1 = a.floor[0].max(b.floor[0]).max(c.floor[0]).min(w1);
            let y0 = a.ceil[1].min(b.ceil[1]).min(c.ceil[1]).max(0);
            let y1 = a.floor[1].max(b.floor[1]).max(c.floor[1]).min(h1);
            if x1 < x0 || y1 < y0 {
                continue;
            }
            let t = ScreenTri {
                p: [a.s, b.s, c.s],
                inv_z: [a.inv_z, b.inv_z, c.inv_z],
                col: if SHADE { tri.map(|i| Vec3::from_array(colours[i as usize])) } else { [Vec3::ZERO; 3] },
                back: SHADE && (b.c - a.c).cross(c.c - a.c).dot(a.c) > 0.0,
            };
            raster_tri::<SHADE>(&t, [x0 as usize, x1 as usize, y0 as usize, y1 as usize], far, zb);
        }
    }

    /// Direct TSDF ray-cast at `camera`: each pixel's ray is marched from `depth_min_m` to
    /// `depth_max_m` (planar), skipping unallocated blocks whole, stepping by
    /// `max(0.8 * tsdf * trunc, voxel / 2)` through observed space, and stops at the first
    /// `+ -> -` zero crossing of the trilinearly interpolated TSDF (all 8 voxels observed,
    /// `weight > 0`); the crossing is refined linearly between the two samples. Colour is
    /// trilinear at the crossing. Only blocks along the rays (inside the frustum) are read.
    /// Parallel over rows.
    pub fn ray_cast(&self, camera: &Camera) -> Rendered {
        let k = camera.intrinsics;
        let (w, h) = (k.width as usize, k.height as usize);
        let mut out = Rendered::empty(k.width, k.height);
        if !camera.world_from_camera.is_finite() || w == 0 {
            return out;
        }
        let rows: Vec<(Vec<Hit>, usize)> = (0..h)
            .into_par_iter()
            .map(|v| {
                let mut visited = 0usize;
                let row = (0..w)
                    .map(|u| {
                        let (hit, n) = self.cast_ray(camera, Vec2::new(u as f32, v as f32));
                        visited += n;
                        hit.unwrap_or((0.0, [0.0; 3]))
                    })
                    .collect();
                (row, visited)
            })
            .collect();
        for (v, (row, n)) in rows.into_iter().enumerate() {
            out.blocks_visited += n;
            for (u, (d, c)) in row.into_iter().enumerate() {
                if d > 0.0 {
                    let i = v * w + u;
                    out.depth_m.data[i] = d;
                    out.colour.data[i] = c;
                    out.covered[i] = true;
                }
            }
        }
        out
    }

    /// One ray: `(Some((depth, colour)), blocks entered)`.
    fn cast_ray(&self, camera: &Camera, uv: Vec2) -> (Option<(f32, [f32; 3])>, usize) {
        let cfg = &self.config;
        let vs = cfg.voxel_size_m;
        let bs = cfg.block_size_m();
        let trunc = cfg.trunc_m();
        let dir_c = camera.intrinsics.ray_z1(uv);
        let len = dir_c.length();
        let dir = camera.world_from_camera.transform_vector(dir_c);
        let origin = camera.world_from_camera.translation;
        let mut t = cfg.depth_min_m.max(1e-4);
        let t_far = cfg.depth_max_m;
        let mut prev: Option<(f32, f32)> = None;
        let mut cache = BlockCache::default();
        let mut entered = 0usize;
        let mut last_block = IVec3::MAX;
        let mut guard = 0;
        while t <= t_far && guard < 1_000_000 {
            guard += 1;
            let p = origin + dir * t;
            let bkey = floor_ivec3(p / bs);
            if bkey != last_block {
                last_block = bkey;
                if self.layer.contains(bkey) {
                    entered += 1;
                } else {
                    // Skip the unallocated block: every trilinear stencil of a point in it reads it.
                    let lo = bkey.as_vec3() * bs;
                    let hi = lo + Vec3::splat(bs);
                    let mut t_exit = f32::INFINITY;
                    for a in 0..3 {
                        if dir[a] > 0.0 {
                            t_exit = t_exit.min((hi[a] - origin[a]) / dir[a]);
                        } else if dir[a] < 0.0 {
                            t_exit = t_exit.min((lo[a] - origin[a]) / dir[a]);
                        }
                    }
                    t = t_exit.max(t) + 1e-4 * vs / len;
                    prev = None;
                    continue;
                }
            }
            match self.trilinear(p, &mut cache) {
                Some((s, _)) => {
                    if let Some((tp, sp)) = prev {
                        if sp >= 0.0 && s < 0.0 {
                            let tc = tp + (t - tp) * sp / (sp - s);
                            let colour =
                                self.trilinear(origin + dir * tc, &mut cache).map(|(_, c)| c).unwrap_or([0.0; 3]);
                            return (Some((tc, colour)), entered);
                        }
                    }
                    prev = Some((t, s));
                    let step_m = (0.8 * s * trunc).max(0.5 * vs);
                    t += step_m / len;
                }
                None => {
                    prev = None;
                    t += 0.5 * vs / len;
                }
            }
        }
        (None, entered)
    }

    /// Trilinear TSDF and colour at world point `p`; `None` unless all 8 voxels are observed.
    fn trilinear<'a>(&'a self, p: Vec3, cache: &mut BlockCache<'a>) -> Option<(f32, [f32; 3])> {
        let q = p / self.config.voxel_size_m - Vec3::splat(0.5);
        let g0 = floor_ivec3(q);
        let f = q - g0.as_vec3();
        let mut tsdf = 0.0;
        let mut colour = Vec3::ZERO;
        for c in 0..8 {
            let o = IVec3::new(c & 1, (c >> 1) & 1, c >> 2);
            let v = cache.voxel(self, g0 + o)?;
            if v.weight <= 0.0 {
                return None;
            }
            let wx = if o.x == 1 { f.x } else { 1.0 - f.x };
            let wy = if o.y == 1 { f.y } else { 1.0 - f.y };
            let wz = if o.z == 1 { f.z } else { 1.0 - f.z };
            let wgt = wx * wy * wz;
            tsdf += wgt * v.tsdf;
            colour += wgt * Vec3::from_array(v.colour);
        }
        Some((tsdf, colour.to_array()))
    }
}

/// Remembers the last block looked up along a ray.
#[derive(Default)]
struct BlockCache<'a> {
    key: Option<IVec3>,
    block: Option<&'a Block>,
}

impl<'a> BlockCache<'a> {
    #[inline]
    fn voxel(&mut self, map: &'a TsdfMap, g: IVec3) -> Option<Voxel> {
        let k = block_of_voxel(g);
        if self.key != Some(k) {
            self.key = Some(k);
            self.block = map.layer.block_at(k);
        }
        let l = voxel_in_block(g);
        self.block.map(|b| b.voxel(local_index(l.x, l.y, l.z)))
    }
}

impl std::fmt::Debug for BlockCache<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlockCache").field("key", &self.key).finish()
    }
}

/// A per-chunk z-buffer: `1/z` (0 = empty), and colour and facing per pixel when shading
/// (empty otherwise).
struct ZBuffer {
    width: usize,
    inv_z: Vec<f32>,
    colour: Vec<[f32; 3]>,
    back: Vec<bool>,
}

impl ZBuffer {
    fn new(width: usize, height: usize, shade: bool) -> Self {
        let n = width * height;
        let m = if shade { n } else { 0 };
        Self { width, inv_z: vec![0.0; n], colour: vec![[0.0; 3]; m], back: vec![false; m] }
    }
}

/// The buffer holding the nearest hit at pixel `i` (on exact ties the earliest).
#[inline]
fn nearest_buffer(buffers: &[ZBuffer], i: usize) -> &ZBuffer {
    let mut best = &buffers[0];
    for b in &buffers[1..] {
        if b.inv_z[i] > best.inv_z[i] {
            best = b;
        }
    }
    best
}

/// Rasterizes one triangle over the pixel-centre box `[x0, x1, y0, y1]` (inclusive); writes
/// colour and facing too when `SHADE`.
#[inline]
fn raster_tri<const SHADE: bool>(t: &ScreenTri, [x0, x1, y0, y1]: [usize; 4], far: f32, zb: &mut ZBuffer) {
    let [a, b, c] = t.p;
    let area = (b - a).perp_dot(c - a);
    if area.abs() < 1e-12 || !area.is_finite() {
        return;
    }
    let inv_area = 1.0 / area;
    let min_inv_z = 1.0 / far;
    for y in y0..y1 + 1 {
        let py = y as f32;
        let row = y * zb.width;
        if !SHADE {
            // Depth only: branch-free (tiny triangles make the inside test unpredictable); the
            // same arithmetic and comparisons as below, so the same depth.
            for (x, cur) in (x0..x1 + 1).zip(&mut zb.inv_z[row + x0..row + x1 + 1]) {
                let p = Vec2::new(x as f32, py);
                let l0 = (c - b).perp_dot(p - b) * inv_area;
                let l1 = (a - c).perp_dot(p - c) * inv_area;
                let l2 = (b - a).perp_dot(p - a) * inv_area;
                let inside = (l0 >= -EDGE_EPS) & (l1 >= -EDGE_EPS) & (l2 >= -EDGE_EPS);
                let iz = l0 * t.inv_z[0] + l1 * t.inv_z[1] + l2 * t.inv_z[2];
                let take = inside & (iz > *cur) & (iz >= min_inv_z);
                *cur = if take { iz } else { *cur };
            }
            continue;
        }
        for x in x0..x1 + 1 {
            let p = Vec2::new(x as f32, py);
            // Barycentrics (normalised by the signed area so both windings work). A hair of
            // tolerance so pixels exactly on shared edges are never lost to rounding (a double
            // hit is harmless under the z-test).
            let l0 = (c - b).perp_dot(p - b) * inv_area;
            let l1 = (a - c).perp_dot(p - c) * inv_area;
            let l2 = (b - a).perp_dot(p - a) * inv_area;
            if l0 < -EDGE_EPS || l1 < -EDGE_EPS || l2 < -EDGE_EPS {
                continue;
            }
            let iz = l0 * t.inv_z[0] + l1 * t.inv_z[1] + l2 * t.inv_z[2];
            let i = row + x;
            if iz > zb.inv_z[i] && iz >= min_inv_z {
                zb.inv_z[i] = iz;
                // Perspective-correct colour: interpolate colour / z, divide by 1 / z.
                let col = (l0 * t.inv_z[0] * t.col[0] + l1 * t.inv_z[1] * t.col[1] + l2 * t.inv_z[2] * t.col[2]) / iz;
                zb.colour[i] = col.to_array();
                zb.back[i] = t.back;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::block::floor_i32;
    use sgam_core::Intrinsics;

    /// The 8-lane vertex projection against the scalar formulas, including vertices behind,
    /// on and far off the camera plane, and NaN.
    #[test]
    fn vertex_projection_matches_scalar_formulas() {
        let k = Intrinsics::try_new(64, 48, 50.0, 52.0, 31.5, 23.5).unwrap();
        let camera =
            Camera::new(k, Rigid3::look_at(Vec3::new(0.1, -0.3, 0.2), Vec3::new(0.4, 2.0, 1.0), Vec3::Z).unwrap());
        let camera_from_world = camera.world_from_camera.inverse();
        let eye = camera.world_from_camera.translation;
        let mut positions: Vec<Vec3> = (0..37)
            .map(|i| Vec3::new((i as f32 * 0.37).sin() * 3.0, 2.0 + (i as f32 * 0.11).cos(), (i % 5) as f32 * 0.4))
            .collect();
        positions.extend([
            eye,
            eye + Vec3::new(1e-12, 0.0, 0.0),
            Vec3::splat(1e30),
            Vec3::NAN,
            Vec3::new(0.0, -5.0, 0.0),
        ]);
        let mut out = Vec::new();
        project_vertices(&positions, &camera_from_world, &camera, &mut out);
        assert_eq!(out.len(), positions.len());
        for (p, v) in positions.iter().zip(&out) {
            let c = camera_from_world.transform_point(*p);
            let iz = 1.0 / c.z;
            let s = Vec2::new(k.fx * c.x * iz + k.cx, k.fy * c.y * iz + k.cy);
            let q = s.clamp(Vec2::splat(-1.0e9), Vec2::splat(1.0e9));
            let same = |a: f32, b: f32| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
            assert!(same(v.c.x, c.x) && same(v.c.y, c.y) && same(v.c.z, c.z), "{p}: {:?} vs {c}", v.c);
            assert!(same(v.inv_z, iz) && same(v.s.x, s.x) && same(v.s.y, s.y), "{p}");
            assert_eq!(v.floor, [floor_i32(q.x), floor_i32(q.y)], "{p}: {q}");
            assert_eq!(v.ceil, [-floor_i32(-q.x), -floor_i32(-q.y)], "{p}: {q}");
        }
    }
}
