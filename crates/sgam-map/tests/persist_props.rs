//! Property tests of the map reader: arbitrary bytes and damaged map files never make
//! `TsdfMap::read_from` panic, and every damage to a valid file (any flipped byte, any cut) is
//! an error, never a silently different map.
#![allow(clippy::unwrap_used)]

use proptest::prelude::*;
use sgam_core::{Camera, Image, Intrinsics, RgbdFrame, Rigid3};
use sgam_map::{TsdfConfig, TsdfMap};

/// A small valid map file: a wall 2 m in front of one camera.
fn valid_map_bytes() -> &'static [u8] {
    static BYTES: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    BYTES.get_or_init(|| {
        let camera = Camera::new(Intrinsics::from_fov_x(24, 16, 1.0), Rigid3::IDENTITY);
        let frame =
            RgbdFrame { colour: Image::filled(24, 16, [0.3f32, 0.6, 0.9]), depth_m: Image::filled(24, 16, 2.0) };
        let mut map = TsdfMap::new(TsdfConfig { voxel_size_m: 0.1, trunc_voxels: 3.0, ..TsdfConfig::default() });
        map.integrate(&frame, &camera);
        let mut bytes = Vec::new();
        map.write_to(&mut bytes).unwrap();
        assert!(map.block_count() > 0);
        bytes
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_never_panic(mut bytes in prop::collection::vec(any::<u8>(), 0..256), magic in any::<bool>()) {
        if magic && bytes.len() >= 12 {
            // past the magic and the version, into the header checks
            bytes[..8].copy_from_slice(b"SGAMTSDF");
            bytes[8..12].copy_from_slice(&1u32.to_le_bytes());
        }
        let _ = TsdfMap::read_from(&mut bytes.as_slice());
    }

    #[test]
    fn any_flipped_byte_is_an_error(pos in 0.0f64..1.0, x in 1u8..=255) {
        let mut bytes = valid_map_bytes().to_vec();
        let i = ((bytes.len() - 1) as f64 * pos) as usize;
        bytes[i] ^= x;
        prop_assert!(TsdfMap::read_from(&mut bytes.as_slice()).is_err(), "byte {} flipped by {:#x} was accepted", i, x);
    }

    #[test]
    fn any_cut_or_extension_is_an_error(cut in 0.0f64..1.0, extra in prop::collection::vec(any::<u8>(), 1..8)) {
        let bytes = valid_map_bytes();
        let short = &bytes[..((bytes.len() - 1) as f64 * cut) as usize];
        prop_assert!(TsdfMap::read_from(&mut &short[..]).is_err());
        let mut long = bytes.to_vec();
        long.extend(extra);
        prop_assert!(TsdfMap::read_from(&mut long.as_slice()).is_err());
    }
}

#[test]
fn the_valid_map_reads_back() {
    let map = TsdfMap::read_from(&mut valid_map_bytes()).unwrap();
    assert!(map.block_count() > 0);
}

#[test]
fn configurations_outside_the_bounds_are_refused_naming_the_field() {
    let ok = TsdfConfig::default();
    ok.validate().unwrap();
    for (cfg, field) in [
        (TsdfConfig { voxel_size_m: 1e-9, ..ok }, "voxel_size_m"),
        (TsdfConfig { voxel_size_m: f32::NAN, ..ok }, "voxel_size_m"),
        (TsdfConfig { voxel_size_m: 100.0, ..ok }, "voxel_size_m"),
        (TsdfConfig { trunc_voxels: 1e6, ..ok }, "trunc_voxels"),
        (TsdfConfig { depth_max_m: 1e9, ..ok }, "depth range"),
        (TsdfConfig { depth_max_m: f32::INFINITY, ..ok }, "depth range"),
    ] {
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains(field), "{e}");
    }
}
