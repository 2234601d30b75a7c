//! `sgam synth` writes the authors' CLEVR-Infinite layout; it reads back through the io crate's
//! reader, `sgam fuse` turns it into a mesh, and the mesh sits where the scene description says.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;
use common::ok;

use sgam_core::Vec3;

#[test]
fn synth_dataset_round_trips_through_reader_and_fusion() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("ds");
    let o = out.to_str().unwrap();
    ok(&[
        "synth", "--out", o, "--scenes", "2", "--split", "1/1", "--res", "64", "--grid", "4", "--seed", "7", "--spp",
        "1",
    ]);
    let scene_dir = out.join("train/scene_000007");
    assert!(out.join("test/scene_000008/transforms.json").exists());
    // resumable: a second run skips finished scenes
    let log = ok(&[
        "synth", "--out", o, "--scenes", "2", "--split", "1/1", "--res", "64", "--grid", "4", "--seed", "7", "--spp",
        "1",
    ]);
    assert!(log.contains("2 already finished"), "{log}");
    // the io crate's reader sees the authors' layout with our depth_type
    let seq = sgam_io::Sequence::open(&scene_dir).unwrap();
    assert_eq!(seq.len(), 16);
    assert_eq!(format!("{:?}", seq.layout), "ClevrAuthors");
    let c0 = seq.camera(0);
    assert!((c0.centre_world() - Vec3::new(-20.0, -20.0, 0.0)).length() < 1e-4);
    let f = seq.read_frame(5).unwrap();
    assert!(f.valid_fraction() > 0.99);
    // fuse and compare with the scene description
    let mesh_path = tmp.path().join("m.ply");
    ok(&[
        "fuse",
        scene_dir.to_str().unwrap(),
        "--voxel-size",
        "0.1",
        "--trunc-voxels",
        "4",
        "--depth-max",
        "20",
        "--out",
        mesh_path.to_str().unwrap(),
    ]);
    let mesh = sgam_io::read_ply(&mesh_path).unwrap();
    let scene: sgam_synth::Scene =
        serde_json::from_slice(&std::fs::read(scene_dir.join("scene.json")).unwrap()).unwrap();
    let above_ground: Vec<&Vec3> = mesh.positions.iter().filter(|p| p.z > scene.ground_z_m + 0.3).collect();
    assert!(above_ground.len() > 100, "no objects fused ({} vertices above the ground)", above_ground.len());
    let inside = above_ground
        .iter()
        .filter(|p| {
            scene.objects.iter().any(|o| {
                let (lo, hi) = o.aabb();
                p.cmpge(lo - 0.2).all() && p.cmple(hi + 0.2).all()
            })
        })
        .count();
    let frac = inside as f64 / above_ground.len() as f64;
    assert!(frac > 0.99, "{:.1}% of object vertices lie on a described object", 100.0 * frac);
    let ground = mesh.positions.iter().filter(|p| (p.z - scene.ground_z_m).abs() < 0.1).count();
    assert!(ground > 1000, "ground plane missing ({ground} vertices)");
    // --preload (frames decoded up front, in parallel) fuses the same frames in the same order
    let preloaded = tmp.path().join("m-preload.ply");
    let args = ["--voxel-size", "0.1", "--trunc-voxels", "4", "--depth-max", "20", "--preload", "--out"];
    let mut cmd = vec!["fuse", scene_dir.to_str().unwrap()];
    cmd.extend(args);
    cmd.push(preloaded.to_str().unwrap());
    ok(&cmd);
    assert_eq!(std::fs::read(&preloaded).unwrap(), std::fs::read(&mesh_path).unwrap(), "--preload changed the mesh");
}
