//! Save/load round trips, corrupt streams, and frame-bounded cost.

mod common;

use common::*;
use sgam_core::Vec3;
use sgam_map::{MapError, TsdfConfig, TsdfMap};

fn small_map() -> TsdfMap {
    let scene = [
        Shape::Plane { normal: Vec3::Z, offset: 0.0 },
        Shape::Sphere { centre: Vec3::new(0.0, 0.0, 0.3), radius: 0.3, colour: [0.2, 0.8, 0.4] },
    ];
    let cfg = TsdfConfig {
        voxel_size_m: 0.04,
        trunc_voxels: 3.0,
        depth_min_m: 0.1,
        depth_max_m: 6.0,
        weight_cap: Some(50.0),
        weight_threshold: 1.0,
    };
    let mut map = TsdfMap::new(cfg);
    for eye in [Vec3::new(1.5, 0.0, 1.5), Vec3::new(-1.0, 1.0, 1.5)] {
        let cam = camera(eye, Vec3::ZERO, 64, 48, 50.0);
        map.integrate(&render_analytic(&scene, &cam), &cam);
    }
    map
}

#[test]
fn save_load_is_bit_exact() {
    let mut map = small_map();
    let mut bytes = Vec::new();
    map.write_to(&mut bytes).unwrap();
    let mut loaded = TsdfMap::read_from(&mut bytes.as_slice()).unwrap();
    assert_eq!(loaded.config(), map.config());
    assert_eq!(loaded.block_keys(), map.block_keys());
    for k in map.block_keys() {
        assert_eq!(loaded.block(k), map.block(k));
    }
    let mut again = Vec::new();
    loaded.write_to(&mut again).unwrap();
    assert_eq!(bytes, again);
    assert_eq!(loaded.extract_mesh(), map.extract_mesh());
}

#[test]
fn corrupt_streams_are_errors() {
    let map = small_map();
    let mut bytes = Vec::new();
    map.write_to(&mut bytes).unwrap();
    // Flipped byte in a voxel.
    let mut flipped = bytes.clone();
    let mid = flipped.len() / 2;
    flipped[mid] ^= 0x40;
    assert!(matches!(TsdfMap::read_from(&mut flipped.as_slice()), Err(MapError::ChecksumMismatch { .. })));
    // Truncated.
    for cut in [0, 5, 20, bytes.len() / 3, bytes.len() - 1] {
        let r = TsdfMap::read_from(&mut &bytes[..cut]);
        assert!(matches!(r, Err(MapError::Truncated(_))), "cut at {cut}: {r:?}");
    }
    // Bad magic and version.
    let mut magic = bytes.clone();
    magic[0] = b'X';
    let err = TsdfMap::read_from(&mut magic.as_slice()).unwrap_err();
    assert!(matches!(err, MapError::BadMagic { .. }) && err.to_string().contains("magic"));
    let mut version = bytes.clone();
    version[8] = 9;
    assert!(matches!(
        TsdfMap::read_from(&mut version.as_slice()),
        Err(MapError::UnsupportedVersion { found: 9, supported: 2 })
    ));
    // Trailing garbage.
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(TsdfMap::read_from(&mut longer.as_slice()).is_err());
    // Well-formed streams (valid checksum) holding values no map can contain: a block key near
    // the i32 limit, a NaN tsdf.
    let header = 8 + 4 + 21 + 8 + 8;
    let resealed = |mut b: Vec<u8>| {
        let body = b.len() - 4;
        let crc = crc32fast::hash(&b[..body]);
        b[body..].copy_from_slice(&crc.to_le_bytes());
        b
    };
    let mut key = bytes.clone();
    key[header..header + 4].copy_from_slice(&i32::MAX.to_le_bytes());
    let err = TsdfMap::read_from(&mut resealed(key).as_slice()).unwrap_err();
    assert!(matches!(err, MapError::InvalidContent(_)) && err.to_string().contains("block key"), "{err}");
    let mut nan = bytes.clone();
    nan[header + 20..header + 24].copy_from_slice(&f32::NAN.to_le_bytes());
    let err = TsdfMap::read_from(&mut resealed(nan).as_slice()).unwrap_err();
    assert!(matches!(err, MapError::InvalidContent(_)) && err.to_string().contains("non-finite"), "{err}");
}

#[test]
fn integration_meshing_and_rendering_cost_depends_on_the_frame_not_the_map() {
    let scene = [Shape::Plane { normal: Vec3::Z, offset: 0.0 }];
    let cfg = TsdfConfig {
        voxel_size_m: 0.05,
        trunc_voxels: 4.0,
        depth_min_m: 0.1,
        depth_max_m: 4.0,
        weight_cap: None,
        weight_threshold: 1.0,
    };
    let probe = camera(Vec3::new(0.0, 0.0, 2.0), Vec3::new(0.2, 0.0, 0.0), 64, 48, 50.0);
    let probe_frame = render_analytic(&scene, &probe);

    let mut small = TsdfMap::new(cfg);
    let first = small.integrate(&probe_frame, &probe);
    small.update_mesh();
    let render_small = small.remesh_and_rasterize(&probe);

    // A large map: many frames far away along x, then the same probe frame.
    let mut large = TsdfMap::new(cfg);
    for i in 1..40 {
        let x = 8.0 * i as f32;
        let cam = camera(Vec3::new(x, 0.0, 2.0), Vec3::new(x + 0.2, 0.0, 0.0), 64, 48, 50.0);
        large.integrate(&render_analytic(&scene, &cam), &cam);
    }
    large.update_mesh();
    let before = large.block_count();
    assert!(before > 20 * first.blocks_touched, "{before} blocks vs {}", first.blocks_touched);
    let second = large.integrate(&probe_frame, &probe);
    assert_eq!(second.blocks_touched, first.blocks_touched);
    assert_eq!(second.blocks_allocated, first.blocks_allocated);
    assert_eq!(second.voxels_updated, first.voxels_updated);
    let remeshed = large.update_mesh();
    assert!(remeshed <= 8 * second.blocks_updated);
    let render_large = large.remesh_and_rasterize(&probe);
    assert_eq!(render_large.blocks_visited, render_small.blocks_visited);
    assert_eq!(render_large.depth_m, render_small.depth_m);
    // Integrating the probe again touches the same blocks, allocates none.
    let third = large.integrate(&probe_frame, &probe);
    assert_eq!((third.blocks_touched, third.blocks_allocated), (first.blocks_touched, 0));
    assert!(large.memory_bytes() > small.memory_bytes());
}

#[test]
fn bad_frames_and_poses_do_not_panic() {
    let cfg = TsdfConfig::default();
    assert!(cfg.validate().is_ok());
    assert!(TsdfConfig { voxel_size_m: 0.0, ..cfg }.validate().is_err());
    assert!(TsdfConfig { depth_min_m: 5.0, depth_max_m: 1.0, ..cfg }.validate().is_err());
    let mut map = TsdfMap::new(cfg);
    let cam = camera(Vec3::new(0.0, 0.0, 10.0), Vec3::ZERO, 32, 24, 30.0);
    let mut frame = render_analytic(&[Shape::Plane { normal: Vec3::Z, offset: 0.0 }], &cam);
    frame.depth_m.data[0] = f32::NAN;
    frame.depth_m.data[1] = f32::INFINITY;
    frame.depth_m.data[2] = -3.0;
    let ok = map.integrate(&frame, &cam);
    assert_eq!(ok.pixels_used, 32 * 24 - 3);
    let mut bad = cam;
    bad.world_from_camera.translation.x = f32::NAN;
    assert_eq!(map.integrate(&frame, &bad).voxels_updated, 0);
    assert!(!map.remesh_and_rasterize(&bad).covered.iter().any(|c| *c));
    assert!(!map.ray_cast(&bad).covered.iter().any(|c| *c));
    // A frame smaller than the intrinsics claim (8 x 6 against 32 x 24) is read at its own size:
    // it integrates exactly like the full frame with every pixel outside its 8 x 6 corner made
    // invalid (same stats, bit-identical blocks).
    let frame = render_analytic(&[Shape::Plane { normal: Vec3::Z, offset: 0.0 }], &cam);
    let (mut crop, mut masked) = (sgam_core::RgbdFrame::empty(8, 6), frame.clone());
    for v in 0..24 {
        for u in 0..32 {
            if u < 8 && v < 6 {
                *crop.depth_m.at_mut(u, v) = *frame.depth_m.at(u, v);
                *crop.colour.at_mut(u, v) = *frame.colour.at(u, v);
            } else {
                *masked.depth_m.at_mut(u, v) = 0.0;
            }
        }
    }
    let (mut from_crop, mut from_masked) = (TsdfMap::new(cfg), TsdfMap::new(cfg));
    let stats = from_crop.integrate(&crop, &cam);
    assert_eq!(stats, from_masked.integrate(&masked, &cam));
    assert_eq!(stats.pixels_used, 8 * 6);
    assert!(stats.voxels_updated > 0 && stats.blocks_updated > 0, "{stats:?}");
    assert_eq!(from_crop.block_keys(), from_masked.block_keys());
    for k in from_crop.block_keys() {
        assert_eq!(from_crop.block(k), from_masked.block(k));
    }
    // An all-invalid frame of another size integrates nothing.
    let stats = map.integrate(&sgam_core::RgbdFrame::empty(8, 6), &cam);
    assert_eq!(stats, sgam_map::IntegrateStats::default());
}
