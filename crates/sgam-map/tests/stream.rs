//! A map that lets far super-blocks go and takes them back renders exactly what a map that kept
//! everything renders: a path out along a corridor of objects and back.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{camera, render_analytic, Shape};
use glam::IVec3;
use sgam_core::{Camera, Vec3};
use sgam_map::{EvictedBlock, TsdfConfig, TsdfMap};

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

fn box_distance(p: Vec3, (lo, hi): (Vec3, Vec3)) -> f32 {
    (p - p.clamp(lo, hi)).length()
}

#[test]
fn evicting_far_super_blocks_and_restoring_them_renders_the_same_frames() {
    let config = TsdfConfig { voxel_size_m: 0.1, trunc_voxels: 3.0, depth_max_m: 8.0, ..TsdfConfig::default() };
    let scene = corridor();
    let cams = path();
    let frames: Vec<_> = cams.iter().map(|c| render_analytic(&scene, c)).collect();
    let (mut kept, mut streamed) = (TsdfMap::new(config), TsdfMap::new(config));
    let mut away: Vec<(IVec3, Vec<EvictedBlock>)> = Vec::new();
    let (mut evicted, mut restored, mut fewest) = (0usize, 0usize, f64::INFINITY);
    for i in 0..cams.len() - 1 {
        let (cam, next) = (&cams[i], &cams[i + 1]);
        // take back what this step may touch: integration here, rendering at the next camera
        let near = |m: &TsdfMap, sk: IVec3| {
            [cam, next].iter().any(|c| box_distance(c.centre_world(), m.super_block_box(sk)) <= m.reach_m(c))
        };
        let (back, still): (Vec<_>, Vec<_>) = away.into_iter().partition(|(sk, _)| near(&streamed, *sk));
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
            .filter(|&sk| {
                [cam, next]
                    .iter()
                    .all(|c| box_distance(c.centre_world(), streamed.super_block_box(sk)) > streamed.reach_m(c) + 1.0)
            })
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
            away.push((sk, mine));
        }
        fewest = fewest.min(streamed.block_count() as f64 / kept.block_count().max(1) as f64);
    }
    assert!(evicted > 0 && restored > 0, "evicted {evicted}, restored {restored}: the path must exercise both");
    assert!(fewest < 0.7, "at its farthest the streamed map held {fewest:.2} of the blocks");
    // everything back: the same world mesh
    for (_, blocks) in away {
        streamed.restore_blocks(blocks).unwrap();
    }
    assert_eq!(streamed.block_keys(), kept.block_keys());
    let (a, b) = (kept.extract_mesh(), streamed.extract_mesh());
    assert!(a.positions == b.positions && a.triangles == b.triangles && a.colours == b.colours);
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
