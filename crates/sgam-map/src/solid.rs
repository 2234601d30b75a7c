//! Fusing surfaces as solids: the inside and the back face behind a frame's surface.

use glam::{IVec3, Vec3};
use rayon::prelude::*;
use sgam_core::ground::GroundPlane;
use sgam_core::{Camera, RgbdFrame, Rigid3};

use crate::allocate::{touched_blocks, Usable};
use crate::block::{Block, BLOCK_SIZE, ROWS};
use crate::map::IntegrateStats;
use crate::TsdfMap;

impl TsdfMap {
    /// Closes the surfaces of `frame` (already fused by [`TsdfMap::integrate`]) into solids:
    /// behind a pixel with thickness `t = thickness_m[i] > 0` (planar depth, metres), a voxel at
    /// planar depth `z` with `s = z - d` in `(trunc, t + trunc]` (`d` the pixel's depth) takes
    /// the value `clamp(max(-s, s - t) / trunc, -1, 1)` (`-1` inside, rising through 0 at the
    /// back face `s = t`), weight 1 and the pixel's colour, **if no view has observed it yet**
    /// (weight 0): what the map knows stays, so an invented object's inside never lifts the
    /// ground or fills the space an earlier view saw. The band `s <= trunc` is the front
    /// integration's, whose observation `-s / trunc` is the same for `t >= 2 trunc`. With
    /// `above`, voxels below that plane are left alone (an object's inside does not run on
    /// under the ground).
    ///
    /// A pixel's thickness `<= 0` (or NaN), or a `thickness_m` of another length than the frame,
    /// adds nothing. Changed blocks are marked dirty; new blocks are allocated in sorted order.
    pub fn integrate_behind(
        &mut self,
        frame: &RgbdFrame,
        camera: &Camera,
        thickness_m: &[f32],
        above: Option<&GroundPlane>,
    ) -> IntegrateStats {
        let cfg = self.config;
        let mut stats = IntegrateStats::default();
        let (w, h) = (frame.depth_m.width as usize, frame.depth_m.height as usize);
        let depth = &frame.depth_m.data[..];
        let positive = |x: f32| x.is_finite() && x > 0.0;
        if !camera.world_from_camera.is_finite()
            || !positive(cfg.voxel_size_m)
            || !positive(cfg.trunc_voxels)
            || thickness_m.len() != w * h
            || depth.len() != w * h
        {
            return stats;
        }
        let trunc = cfg.trunc_m();
        let usable = Usable::new(&cfg);
        let deepest = thickness_m.iter().copied().filter(|t| positive(*t)).fold(0.0f32, f32::max);
        if deepest <= 0.0 {
            return stats;
        }
        // Blocks: the segment `d + trunc ..= d + t + trunc` of every thick pixel is covered by
        // bands `c - trunc ..= c + trunc` centred at `c = d + 2 trunc k` (k = 1, 2, ...), the last
        // one at `d + t`.
        let mut keys = rustc_hash::FxHashSet::<IVec3>::default();
        let mut k = 1;
        loop {
            let offset = 2.0 * trunc * k as f32;
            let shifted: Vec<f32> = depth
                .iter()
                .zip(thickness_m)
                .map(|(&d, &t)| {
                    if positive(t) && usable.ok(d) && t + trunc > offset - trunc {
                        d + offset.min(t)
                    } else {
                        f32::NAN
                    }
                })
                .collect();
            let (found, used) = touched_blocks(&shifted, w, h, camera, &cfg);
            stats.pixels_used = stats.pixels_used.max(used);
            keys.extend(found);
            if offset >= deepest {
                break;
            }
            k += 1;
        }
        // a block wholly below the plane would take nothing
        let block_m = cfg.block_size_m();
        let below = |key: IVec3| {
            above.is_some_and(|p| {
                (0..8).all(|c| {
                    let corner = IVec3::new(c & 1, (c >> 1) & 1, c >> 2);
                    p.height((key + corner).as_vec3() * block_m) < 0.0
                })
            })
        };
        let mut keys: Vec<IVec3> = keys.into_iter().filter(|k| !below(*k)).collect();
        keys.sort_unstable_by_key(|k| (k.x, k.y, k.z));
        stats.blocks_touched = keys.len();
        let mut ids = Vec::with_capacity(keys.len());
        for key in keys {
            let (id, new) = self.allocate(key);
            stats.blocks_allocated += new as usize;
            ids.push(id);
        }
        // unique: the keys came from a set
        ids.sort_unstable();
        let ctx = Behind {
            depth,
            thickness: thickness_m,
            colour: if frame.colour.data.len() == w * h { &frame.colour.data } else { &[] },
            width: w,
            height: h,
            camera,
            camera_from_world: camera.world_from_camera.inverse(),
            usable,
            voxel_size_m: cfg.voxel_size_m,
            trunc_m: trunc,
            above: above.copied(),
        };
        let updated: Vec<(u32, usize)> = {
            let (blocks, keys_of) = self.layer.blocks_mut(&ids);
            blocks.into_par_iter().zip(&ids).map(|(b, &id)| (id, ctx.update(b, keys_of[id as usize]))).collect()
        };
        for (id, n) in updated {
            if n > 0 {
                stats.blocks_updated += 1;
                stats.voxels_updated += n;
                self.refresh_sign_flags(id);
                self.mark_dirty(id);
            }
        }
        stats
    }
}

/// Per-frame constants of [`TsdfMap::integrate_behind`].
struct Behind<'a> {
    depth: &'a [f32],
    thickness: &'a [f32],
    colour: &'a [[f32; 3]],
    width: usize,
    height: usize,
    camera: &'a Camera,
    camera_from_world: Rigid3,
    usable: Usable,
    voxel_size_m: f32,
    trunc_m: f32,
    above: Option<GroundPlane>,
}

impl Behind<'_> {
    /// Updates one block's voxels behind thick pixels; returns how many changed.
    fn update(&self, block: &mut Block, key: IVec3) -> usize {
        const N: usize = BLOCK_SIZE as usize;
        let k = self.camera.intrinsics;
        let vs = self.voxel_size_m;
        let planes = &mut *block.planes;
        let mut n = 0;
        for row in 0..ROWS {
            let (y, z) = ((row % N) as i32, (row / N) as i32);
            for x in 0..N {
                let world = ((key * BLOCK_SIZE + IVec3::new(x as i32, y, z)).as_vec3() + Vec3::splat(0.5)) * vs;
                let p = self.camera_from_world.transform_point(world);
                if p.z.is_nan() || p.z <= 0.0 {
                    continue;
                }
                let u = k.fx * p.x / p.z + k.cx + 0.5;
                let v = k.fy * p.y / p.z + k.cy + 0.5;
                let inside = u >= 0.0 && v >= 0.0 && u < self.width as f32 && v < self.height as f32;
                if !inside {
                    continue;
                }
                let i = v as usize * self.width + u as usize;
                let (t, d) = (self.thickness[i], self.depth[i]);
                let thick = t > 0.0 && self.usable.ok(d);
                if !thick {
                    continue;
                }
                let s = p.z - d;
                // only space no view has seen: what the map knows stays (a solid's inside must
                // not lift the ground an earlier view saw behind it)
                let in_segment = s > self.trunc_m && s <= t + self.trunc_m;
                if !in_segment || planes.weight[row][x] > 0.0 {
                    continue;
                }
                if self.above.is_some_and(|g| g.height(world) < 0.0) {
                    continue;
                }
                planes.tsdf[row][x] = ((-s).max(s - t) / self.trunc_m).clamp(-1.0, 1.0);
                planes.weight[row][x] = 1.0;
                if let Some(c) = self.colour.get(i) {
                    for (ch, &value) in c.iter().enumerate() {
                        planes.colour[ch][row][x] = value;
                    }
                }
                n += 1;
            }
        }
        n
    }
}

#[cfg(test)]
mod tests {
    use sgam_core::{Image, Intrinsics, Rigid3};

    use super::*;
    use crate::TsdfConfig;

    const VOXEL: f32 = 0.05;

    fn config() -> TsdfConfig {
        TsdfConfig {
            voxel_size_m: VOXEL,
            trunc_voxels: 5.0,
            depth_min_m: 0.05,
            depth_max_m: 20.0,
            weight_cap: None,
            weight_threshold: 1.0,
        }
    }

    fn camera(world_from_camera: Rigid3) -> Camera {
        let k = Intrinsics { width: 64, height: 64, fx: 64.0, fy: 64.0, cx: 31.5, cy: 31.5 };
        Camera { intrinsics: k, world_from_camera }
    }

    /// A red wall 4 m in front of a camera at the origin looking along +z, fused.
    fn wall() -> (TsdfMap, Camera, RgbdFrame) {
        let cam = camera(Rigid3::IDENTITY);
        let frame = RgbdFrame { colour: Image::filled(64, 64, [1.0, 0.0, 0.0]), depth_m: Image::filled(64, 64, 4.0) };
        let mut map = TsdfMap::new(config());
        map.integrate(&frame, &cam);
        (map, cam, frame)
    }

    /// The voxel on the optical axis (just off it: voxel centres are at half-voxels) at depth z.
    fn on_axis(map: &TsdfMap, y_voxel: i32, z_m: f32) -> Option<crate::Voxel> {
        map.voxel(IVec3::new(0, y_voxel, (z_m / VOXEL).floor() as i32))
    }

    #[test]
    fn behind_a_thick_surface_is_inside_then_a_back_face() {
        let (mut map, cam, frame) = wall();
        assert!(on_axis(&map, 0, 4.52).is_none_or(|v| v.weight == 0.0), "nothing beyond the band before");
        let thickness = vec![1.0; 64 * 64];
        let stats = map.integrate_behind(&frame, &cam, &thickness, None);
        assert!(stats.voxels_updated > 0 && stats.blocks_allocated > 0, "{stats:?}");
        // voxel centres at z = 4.525 (inside), 4.975 (0.025 before the back face at 5.0),
        // 5.175 (behind it), 5.275 (past the back face's band)
        let inside = on_axis(&map, 0, 4.52).unwrap();
        assert_eq!((inside.tsdf, inside.weight), (-1.0, 1.0));
        assert_eq!(inside.colour, [1.0, 0.0, 0.0]);
        let near_back = on_axis(&map, 0, 4.97).unwrap();
        assert!((near_back.tsdf + 0.1).abs() < 1e-4, "{near_back:?}");
        let behind = on_axis(&map, 0, 5.17).unwrap();
        assert!((behind.tsdf - 0.7).abs() < 1e-4, "{behind:?}");
        assert!(on_axis(&map, 0, 5.27).is_none_or(|v| v.weight == 0.0));
        // the front band is the front integration's alone
        let front = on_axis(&map, 0, 4.12).unwrap();
        assert_eq!(front.weight, 1.0);
        // seen from behind, the map now ends at the back face, 5 m from the first camera
        let back_cam = camera(Rigid3 {
            rotation: glam::Mat3::from_rotation_y(std::f32::consts::PI),
            translation: Vec3::new(0.0, 0.0, 10.0),
        });
        let depth = map.remesh_and_rasterize_depth(&back_cam);
        let d = *depth.at(32, 32);
        assert!((d - 5.0).abs() < 0.06, "rendered from behind: {d}");
    }

    #[test]
    fn nothing_below_the_plane_and_nothing_without_thickness() {
        let (mut map, cam, frame) = wall();
        let before = map.clone();
        let stats = map.integrate_behind(&frame, &cam, &vec![0.0; 64 * 64], None);
        assert_eq!(stats.voxels_updated, 0);
        assert_eq!(map.block_keys(), before.block_keys());
        // a thickness of the wrong length adds nothing either
        assert_eq!(map.integrate_behind(&frame, &cam, &[1.0; 10], None).voxels_updated, 0);
        // the ground: y = 0 (OpenCV y points down, so up is -y); voxels below it are left alone
        let plane = GroundPlane { normal: Vec3::new(0.0, -1.0, 0.0), offset: 0.0, inlier_fraction: 1.0 };
        map.integrate_behind(&frame, &cam, &vec![1.0; 64 * 64], Some(&plane));
        // voxel row y = -10 is 0.475 m above the plane; y = 9 is 0.475 m below
        assert_eq!(on_axis(&map, -10, 4.52).unwrap().tsdf, -1.0);
        assert!(on_axis(&map, 9, 4.52).is_none_or(|v| v.weight == 0.0));
        // space a view has seen keeps its value: a wall 5 m away, fused first, saw the voxel at
        // 4.525 m as free; the 4 m wall's inside does not take it
        let mut seen = TsdfMap::new(config());
        let far = RgbdFrame { colour: frame.colour.clone(), depth_m: Image::filled(64, 64, 5.0) };
        seen.integrate(&far, &cam);
        seen.integrate(&frame, &cam);
        let free = on_axis(&seen, 0, 4.52).unwrap();
        assert_eq!((free.tsdf, free.weight), (1.0, 1.0));
        seen.integrate_behind(&frame, &cam, &vec![1.0; 64 * 64], None);
        assert_eq!(on_axis(&seen, 0, 4.52).unwrap(), free);
        // no block lies wholly below the plane
        let block_m = VOXEL * BLOCK_SIZE as f32;
        assert!(map.block_keys().iter().all(|k| (k.y as f32) * block_m <= 0.0 || before.block_keys().contains(k)));
    }
}
