//! A map that lets far super-blocks go and takes them back renders exactly what a map that kept
//! everything renders: a path out along a corridor of objects and back.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{camera, render_analytic, Shape};
use glam::IVec3;
use sgam_core::{Camera, Vec3};
use sgam_map::{read_tile, write_tile, EvictedBlock, MapError, TsdfConfig, TsdfMap};

fn corridor() -> Vec<Shape> {
    let mut s = vec![Shape::Plane { normal: Vec3::Z, offset: 0.0 }];
    for i in 0..20 {
        let x = 2.0 + 2.5 * i as f32;
        let y = if i % 2 == 0 { 1.2 } else { -1.4 };
        if i % 3 == 0 {
            s.push(Shape::Sphere { centre: Vec3::new(x, y, 0.5), radius: 0.5, colour: [0.8, 0.2, 0.2] });
        } else {
            s.push(Shape::Cuboid {
                min: Vec3::new(x - 0.4, y - 0.4, 0.0),
                max: Vec3::new(x + 0.4, y + 0.4, 0.9),
                colour: [0.2, 0.3, 0.8],
            });
        }
    }
    s
}

/// Out along +x to 40 m looking ahead, then back looking the other way.
fn path() -> Vec<Camera> {
    let out = (0..=20).map(|i| 2.0 * i as f32);
    let back = (0..=20).rev().map(|i| 2.0 * i as f32);
    out.map(|x| camera(Vec3::new(x, 0.0, 1.6), Vec3::new(x + 5.0, 0.0, 0.0), 64, 48, 48.0))
        .chain(back.map(|x| camera(Vec3::new(x, 0.0, 1.6), Vec3::new(x - 5.0, 0.0, 0.0), 64, 48, 48.0)))
        .collect()
}

/// `blocks` of super-block `sk` written to a tile and read back (and written again: the same
/// bytes).
fn through_tile(config: &TsdfConfig, sk: IVec3, blocks: Vec<EvictedBlock>) -> Vec<EvictedBlock> {
    let mut bytes = Vec::new();
    write_tile(&mut bytes, config, sk, &blocks).unwrap();
    let (key, back) = read_tile(&bytes, config).unwrap();
    assert_eq!((key, back.len()), (sk, blocks.len()));
    let mut again = Vec::new();
    write_tile(&mut again, config, sk, &back).unwrap();
    assert!(again == bytes, "a tile read back writes other bytes");
    back
}

fn box_distance(p: Vec3, (lo, hi): (Vec3, Vec3)) -> f32 {
    (p - p.clamp(lo, hi)).length()
}

/// Whether super-block `sk` lies within `grow_m` of what a step at `c` may read or write.
type Reach = fn(&TsdfMap, &Camera, f32, IVec3) -> bool;

/// The sphere of the map's reach around the camera.
fn sphere(m: &TsdfMap, c: &Camera, grow_m: f32, sk: IVec3) -> bool {
    box_distance(c.centre_world(), m.super_block_box(sk)) <= m.reach_m(c) + grow_m
}

/// The camera's grown frustum.
fn view(m: &TsdfMap, c: &Camera, grow_m: f32, sk: IVec3) -> bool {
    m.view_reach(c, grow_m).touches(m.super_block_box(sk))
}

#[test]
fn evicting_far_super_blocks_and_restoring_them_renders_the_same_frames() {
    let fewest = out_and_back(sphere);
    assert!(fewest < 0.7, "at its farthest the streamed map held {fewest:.2} of the blocks");
}

#[test]
fn evicting_outside_the_view_renders_the_same_frames_and_keeps_less() {
    let by_view = out_and_back(view);
    let by_sphere = out_and_back(sphere);
    // the way back looks away from everything the way out left behind the camera
    assert!(by_view < 0.8 * by_sphere, "view-shaped kept {by_view:.2} of the blocks, the sphere {by_sphere:.2}");
}

#[test]
fn what_an_integration_touches_lies_in_its_view_reach() {
    let config = TsdfConfig { voxel_size_m: 0.05, trunc_voxels: 4.0, depth_max_m: 6.0, ..TsdfConfig::default() };
    let scene = corridor();
    for (i, cam) in path().iter().enumerate().step_by(5) {
        let mut m = TsdfMap::new(config);
        m.integrate(&render_analytic(&scene, cam), cam);
        m.update_mesh();
        let reach = m.view_reach(cam, 0.0);
        assert!(m.block_count() > 0);
        let bs = config.block_size_m();
        for k in m.block_keys() {
            let lo = k.as_vec3() * bs;
            assert!(reach.touches((lo, lo + Vec3::splat(bs))), "camera {i}: block {k} outside its view reach");
        }
        // and the region is no sphere: a box behind the camera is outside it
        let behind = cam.world_from_camera.transform_point(Vec3::new(0.0, 0.0, -5.0));
        assert!(!reach.touches((behind - Vec3::splat(0.5), behind + Vec3::splat(0.5))), "camera {i}");
        let ahead = cam.world_from_camera.transform_point(Vec3::new(0.0, 0.0, 3.0));
        assert!(reach.touches((ahead - Vec3::splat(0.1), ahead + Vec3::splat(0.1))), "camera {i}");
        let beyond = cam.world_from_camera.transform_point(Vec3::new(0.0, 0.0, 12.0));
        assert!(!reach.touches((beyond - Vec3::splat(0.1), beyond + Vec3::splat(0.1))), "camera {i}");
    }
}

/// Runs the corridor out and back on a map that lets go of what `near` does not hold and one
/// that keeps everything; every frame equal (asserted). Returns the smallest share of the kept
/// map's blocks the streamed map held.
fn out_and_back(near: Reach) -> f64 {
    let config = TsdfConfig { voxel_size_m: 0.1, trunc_voxels: 3.0, depth_max_m: 8.0, ..TsdfConfig::default() };
    let scene = corridor();
    let cams = path();
    let frames: Vec<_> = cams.iter().map(|c| render_analytic(&scene, c)).collect();
    let (mut kept, mut streamed) = (TsdfMap::new(config), TsdfMap::new(config));
    let mut away: Vec<(IVec3, Vec<EvictedBlock>)> = Vec::new();
    let (mut evicted, mut restored, mut fewest, mut saved) = (0usize, 0usize, f64::INFINITY, false);
    for i in 0..cams.len() - 1 {
        let (cam, next) = (&cams[i], &cams[i + 1]);
        // take back what this step may touch: integration here, rendering at the next camera
        let (back, still): (Vec<_>, Vec<_>) =
            away.into_iter().partition(|(sk, _)| [cam, next].iter().any(|c| near(&streamed, c, 0.0, *sk)));
        away = still;
        for (_, blocks) in back {
            restored += blocks.len();
            streamed.restore_blocks(blocks).unwrap();
        }
        for m in [&mut kept, &mut streamed] {
            m.integrate(&frames[i], cam);
            m.update_mesh();
        }
        let a = kept.rasterize(next);
        let b = streamed.rasterize(next);
        assert!(a.depth_m.data == b.depth_m.data, "step {i}: depth differs after eviction");
        assert!(a.colour.data == b.colour.data, "step {i}: colour differs after eviction");
        // let go of what neither camera can reach, with 1 m to spare
        let far: Vec<IVec3> = streamed
            .super_block_keys()
            .into_iter()
            .filter(|&sk| [cam, next].iter().all(|c| !near(&streamed, c, 1.0, sk)))
            .collect();
        let mut blocks = streamed.evict_super_blocks(&far);
        evicted += blocks.len();
        for sk in far {
            let mine: Vec<EvictedBlock> = {
                let (m, rest): (Vec<_>, Vec<_>) =
                    blocks.into_iter().partition(|b| sgam_map::super_block_of(b.key) == sk);
                blocks = rest;
                m
            };
            away.push((sk, through_tile(&config, sk, mine)));
        }
        // at the far end, the streamed map goes through its file and on from there, as a
        // resumed run does (the blocks away stay away)
        if i == cams.len() / 2 {
            // the tiles away, each rendered alone and merged with the resident part, draw
            // what the whole map draws from high above
            let above = camera(Vec3::new(20.0, 0.0, 20.0), Vec3::new(20.0, 0.01, 0.0), 96, 64, 40.0);
            let whole = kept.rasterize_range(&above, 1.0, 100.0);
            let mut merged = streamed.rasterize_range(&above, 1.0, 100.0);
            for (_, blocks) in &away {
                let tile = TsdfMap::from_evicted(config, blocks.clone()).unwrap();
                merged.merge_nearer(&tile.rasterize_range(&above, 1.0, 100.0)).unwrap();
            }
            assert!(whole.covered.iter().filter(|c| **c).count() > 500);
            assert!(merged.covered == whole.covered && merged.depth_m.data == whole.depth_m.data);
            let mut bytes = Vec::new();
            streamed.write_to(&mut bytes).unwrap();
            streamed = TsdfMap::read_from(&mut bytes.as_slice()).unwrap();
            // as a resumed run does: the tiles next to a resident super-block on its upper sides
            // come back, and the loaded blocks (which the file holds without meshes) are meshed
            // with them
            let resident: Vec<IVec3> = streamed.super_block_keys();
            let (back, still): (Vec<_>, Vec<_>) = away.into_iter().partition(|(sk, _)| {
                (1..8).any(|o| resident.contains(&(*sk - IVec3::new(o & 1, (o >> 1) & 1, o >> 2))))
            });
            away = still;
            for (_, blocks) in back {
                streamed.restore_blocks(blocks).unwrap();
            }
            streamed.remesh_dirty_only();
            saved = true;
        }
        fewest = fewest.min(streamed.block_count() as f64 / kept.block_count().max(1) as f64);
    }
    assert!(evicted > 0 && restored > 0, "evicted {evicted}, restored {restored}: the path must exercise both");
    assert!(saved);
    // everything back: the same world mesh
    for (_, blocks) in away {
        streamed.restore_blocks(blocks).unwrap();
    }
    assert_eq!(streamed.block_keys(), kept.block_keys());
    let (a, b) = (kept.extract_mesh(), streamed.extract_mesh());
    assert!(a.positions == b.positions && a.triangles == b.triangles && a.colours == b.colours);
    // the world mesh is the union of the super-blocks' meshes
    let parts: usize = kept.super_block_keys().into_iter().map(|sk| kept.super_block_mesh(sk).triangles.len()).sum();
    assert_eq!(parts, a.triangles.len());
    fewest
}

#[test]
fn a_block_is_restored_once_and_only_into_its_own_map() {
    let config = TsdfConfig { voxel_size_m: 0.1, trunc_voxels: 3.0, depth_max_m: 8.0, ..TsdfConfig::default() };
    let cams = path();
    let frame = render_analytic(&corridor(), &cams[0]);
    let mut m = TsdfMap::new(config);
    m.integrate(&frame, &cams[0]);
    let keys = m.super_block_keys();
    let blocks = m.evict_super_blocks(&keys[..1]);
    assert!(!blocks.is_empty());
    let copy = blocks.clone();
    m.restore_blocks(blocks).unwrap();
    let e = m.restore_blocks(copy.clone()).unwrap_err().to_string();
    assert!(e.contains("already in the map"), "{e}");
    let e = TsdfMap::new(config).restore_blocks(copy).unwrap_err().to_string();
    assert!(e.contains("another map"), "{e}");
}

#[test]
fn a_damaged_or_foreign_tile_is_an_error_never_a_panic() {
    let config = TsdfConfig { voxel_size_m: 0.1, trunc_voxels: 3.0, depth_max_m: 8.0, ..TsdfConfig::default() };
    let cams = path();
    let mut m = TsdfMap::new(config);
    m.integrate(&render_analytic(&corridor(), &cams[0]), &cams[0]);
    m.update_mesh();
    let sk = m.super_block_keys()[0];
    let blocks = m.evict_super_blocks(&[sk]);
    let mut bytes = Vec::new();
    write_tile(&mut bytes, &config, sk, &blocks).unwrap();
    // every flipped byte and every cut is refused
    for i in (0..bytes.len()).step_by(bytes.len() / 97 + 1) {
        let mut b = bytes.clone();
        b[i] ^= 0x5a;
        assert!(read_tile(&b, &config).is_err(), "byte {i} flipped was accepted");
    }
    for cut in [0, 7, 11, 30, bytes.len() / 2, bytes.len() - 1] {
        assert!(read_tile(&bytes[..cut], &config).is_err(), "cut at {cut} was accepted");
    }
    // another map's voxels, another format
    let other = TsdfConfig { voxel_size_m: 0.05, ..config };
    let e = read_tile(&bytes, &other).unwrap_err().to_string();
    assert!(e.contains("0.1 m voxels") && e.contains("0.05 m voxels"), "{e}");
    let mut map_file = Vec::new();
    m.write_to(&mut map_file).unwrap();
    assert!(matches!(read_tile(&map_file, &config), Err(MapError::BadMagic { .. })));
    // a block given under the wrong super-block is refused at writing
    let e = write_tile(&mut Vec::new(), &config, sk + IVec3::X, &blocks).unwrap_err().to_string();
    assert!(e.contains("not in super-block"), "{e}");
}

#[test]
fn a_map_file_keeps_allocation_order_and_a_version_1_file_still_loads() {
    let config = TsdfConfig { voxel_size_m: 0.1, trunc_voxels: 3.0, depth_max_m: 8.0, ..TsdfConfig::default() };
    let cams = path();
    let mut m = TsdfMap::new(config);
    for c in &cams[..6] {
        m.integrate(&render_analytic(&corridor(), c), c);
    }
    // the blocks of a far super-block go, the map is saved and loaded, they come back: only a
    // loaded map that kept allocation order takes them
    let far = *m.super_block_keys().last().unwrap();
    let away = m.evict_super_blocks(&[far]);
    assert!(!away.is_empty());
    let mut bytes = Vec::new();
    m.write_to(&mut bytes).unwrap();
    let mut loaded = TsdfMap::read_from(&mut bytes.as_slice()).unwrap();
    loaded.restore_blocks(away.clone()).unwrap();
    m.restore_blocks(away).unwrap();
    let (mut a, mut b) = (Vec::new(), Vec::new());
    m.write_to(&mut a).unwrap();
    loaded.write_to(&mut b).unwrap();
    assert!(a == b, "a map saved, loaded and given its blocks back differs from the one that kept them");
    m.update_mesh();
    loaded.update_mesh();
    assert!(m.rasterize(&cams[8]).depth_m.data == loaded.rasterize(&cams[8]).depth_m.data);
    // version 1: no next order, no per-block order (blocks take key order)
    let header = 8 + 4 + 21;
    let mut v1 = bytes[..header].to_vec();
    v1[8..12].copy_from_slice(&1u32.to_le_bytes());
    v1.extend_from_slice(&bytes[header + 8..header + 16]);
    let block = 12 + 8 + 512 * 20;
    for chunk in bytes[header + 16..bytes.len() - 4].chunks(block) {
        v1.extend_from_slice(&chunk[..12]);
        v1.extend_from_slice(&chunk[20..]);
    }
    let crc = crc32fast::hash(&v1);
    v1.extend_from_slice(&crc.to_le_bytes());
    let old = TsdfMap::read_from(&mut v1.as_slice()).unwrap();
    assert_eq!(
        old.block_keys(),
        m.block_keys().into_iter().filter(|k| sgam_map::super_block_of(*k) != far).collect::<Vec<_>>()
    );
}

#[test]
fn taking_one_neighbour_back_leaves_the_meshes_that_read_another_still_away() {
    // a block whose +x neighbour comes back while its +y neighbour stays away keeps the mesh
    // it had: re-meshing it then would lose its cells towards +y
    let config = TsdfConfig { voxel_size_m: 0.1, trunc_voxels: 3.0, depth_max_m: 8.0, ..TsdfConfig::default() };
    let cams = path();
    let mut kept = TsdfMap::new(config);
    for c in &cams[..8] {
        kept.integrate(&render_analytic(&corridor(), c), c);
    }
    kept.update_mesh();
    let supers = kept.super_block_keys();
    let has = |k: IVec3| supers.contains(&k);
    let s = *supers
        .iter()
        .find(|&&k| has(k + IVec3::X) && has(k + IVec3::Y))
        .expect("a super-block with +x and +y neighbours");
    let mut m = kept.clone();
    let away = m.evict_super_blocks(&[s + IVec3::X, s + IVec3::Y]);
    let (back, still): (Vec<EvictedBlock>, Vec<EvictedBlock>) =
        away.into_iter().partition(|b| sgam_map::super_block_of(b.key) == s + IVec3::X);
    assert!(!back.is_empty() && !still.is_empty());
    m.restore_blocks(back).unwrap();
    m.update_mesh();
    let (a, b) = (kept.super_block_mesh(s), m.super_block_mesh(s));
    assert!(a.triangles.len() > 100);
    assert!(
        a.positions == b.positions && a.triangles == b.triangles,
        "{} against {} triangles",
        b.triangles.len(),
        a.triangles.len()
    );
}

#[test]
fn a_tile_with_a_valid_checksum_and_a_key_beyond_the_map_is_refused() {
    // crafted, not damaged: the CRC matches, the key is far outside any map (i32::MIN too)
    let config = TsdfConfig { voxel_size_m: 0.1, trunc_voxels: 3.0, depth_max_m: 8.0, ..TsdfConfig::default() };
    for far in [i32::MIN, i32::MAX, 1 << 29] {
        let key = IVec3::new(far, 0, 0);
        let sk = sgam_map::super_block_of(key);
        let mut bytes = Vec::new();
        bytes.extend_from_slice(b"SGAMTILE");
        bytes.extend_from_slice(&1u32.to_le_bytes());
        bytes.extend_from_slice(&0.1f32.to_le_bytes());
        for v in sk.to_array() {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        bytes.extend_from_slice(&1u32.to_le_bytes());
        for v in key.to_array() {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        bytes.extend_from_slice(&0u64.to_le_bytes()); // order
        bytes.extend_from_slice(&[0u8; 64]); // no voxel stored
        bytes.extend_from_slice(&[0u8; 9]); // no mesh
        let crc = crc32fast::hash(&bytes);
        bytes.extend_from_slice(&crc.to_le_bytes());
        let e = read_tile(&bytes, &config).unwrap_err().to_string();
        assert!(e.contains("outside"), "{far}: {e}");
    }
}
