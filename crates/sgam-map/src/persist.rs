//! Versioned binary persistence of a [`TsdfMap`].
//!
//! Layout (all little-endian):
//! ```text
//! magic      8 bytes  "SGAMTSDF"
//! version    u32      2
//! config     f32 voxel_size_m, f32 trunc_voxels, f32 depth_min_m, f32 depth_max_m,
//!            u8 has_cap, f32 weight_cap (0 when none)
//! next order u64      the next allocation's place in allocation order
//! blocks     u64 count, then per block in ascending (x, y, z) key order:
//!            i32 x, i32 y, i32 z, u64 allocation order,
//!            512 voxels x (f32 tsdf, f32 weight, f32 r, f32 g, f32 b)
//! crc32      u32      CRC-32 (IEEE) of every preceding byte
//! ```
//! Version 1 (still read) had no allocation order: its blocks take their place in key order.
//! The order is what the rasterizer breaks ties by, and what lets blocks written to tiles
//! ([`crate::stream`]) come back into a map that was saved and loaded in between.
//! Meshes are not stored; a loaded map re-meshes everything on the first extraction.

use std::io::{Read, Write};

use glam::IVec3;

use crate::block::{Block, Voxel, BLOCK_VOXELS};
use crate::{MapError, TsdfConfig, TsdfMap};

const MAGIC: &[u8; 8] = b"SGAMTSDF";
const VERSION: u32 = 2;
/// Header bytes of version 1 and of version 2 (which adds the next order).
const HEADER_BYTES_V1: usize = 8 + 4 + 21 + 8;
const HEADER_BYTES: usize = HEADER_BYTES_V1 + 8;
const BLOCK_BYTES_V1: usize = 12 + BLOCK_VOXELS * 20;
const BLOCK_BYTES: usize = BLOCK_BYTES_V1 + 8;
/// Largest block-key coordinate a loaded map may hold: voxel indices (`8 key`) and neighbour
/// keys stay far from `i32` overflow (2^28 blocks is ~10^7 km at 5 cm voxels).
pub(crate) const MAX_BLOCK_KEY: i32 = 1 << 28;

impl TsdfMap {
    /// Writes the map in the versioned binary format described in this module (blocks sorted
    /// by key, so equal maps give identical bytes), ending with a CRC-32.
    pub fn write_to(&self, w: &mut impl Write) -> Result<(), MapError> {
        let mut ids: Vec<u32> = (0..self.layer.len() as u32).collect();
        ids.sort_unstable_by_key(|&i| {
            let k = self.layer.key(i);
            (k.x, k.y, k.z)
        });
        // written a block at a time through the checksum, so saving a large map needs no copy
        // of it in memory
        let mut out = Crc32Writer { w, crc: crc32fast::Hasher::new() };
        let mut buf = Vec::with_capacity(BLOCK_BYTES);
        buf.extend_from_slice(MAGIC);
        buf.extend_from_slice(&VERSION.to_le_bytes());
        let c = &self.config;
        for v in [c.voxel_size_m, c.trunc_voxels, c.depth_min_m, c.depth_max_m] {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        buf.push(c.weight_cap.is_some() as u8);
        buf.extend_from_slice(&c.weight_cap.unwrap_or(0.0).to_le_bytes());
        buf.extend_from_slice(&self.next_order.to_le_bytes());
        buf.extend_from_slice(&(ids.len() as u64).to_le_bytes());
        out.write_all(&buf)?;
        for id in ids {
            buf.clear();
            let k = self.layer.key(id);
            for v in [k.x, k.y, k.z] {
                buf.extend_from_slice(&v.to_le_bytes());
            }
            buf.extend_from_slice(&self.order[id as usize].to_le_bytes());
            for vox in self.layer.block(id).voxels() {
                for v in [vox.tsdf, vox.weight, vox.colour[0], vox.colour[1], vox.colour[2]] {
                    buf.extend_from_slice(&v.to_le_bytes());
                }
            }
            out.write_all(&buf)?;
        }
        let crc = out.crc.finalize();
        out.w.write_all(&crc.to_le_bytes())?;
        out.w.flush()?;
        Ok(())
    }

    /// Reads a map written by [`TsdfMap::write_to`]. Errors on wrong magic, unsupported version,
    /// truncation, checksum mismatch, an invalid configuration or duplicate block keys. All
    /// blocks are marked dirty, so the first extraction re-meshes the map.
    pub fn read_from(r: &mut impl Read) -> Result<TsdfMap, MapError> {
        let mut bytes = Vec::new();
        r.read_to_end(&mut bytes)?;
        if bytes.len() < 12 {
            if bytes.len() >= 8 && &bytes[..8] != MAGIC {
                return Err(bad_magic(&bytes));
            }
            return Err(MapError::Truncated(format!("{} bytes, shorter than the header", bytes.len())));
        }
        if &bytes[..8] != MAGIC {
            return Err(bad_magic(&bytes));
        }
        let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
        if !(1..=VERSION).contains(&version) {
            return Err(MapError::UnsupportedVersion { found: version, supported: VERSION });
        }
        let (header_bytes, block_bytes) =
            if version == 1 { (HEADER_BYTES_V1, BLOCK_BYTES_V1) } else { (HEADER_BYTES, BLOCK_BYTES) };
        if bytes.len() < header_bytes + 4 {
            return Err(MapError::Truncated(format!("{} bytes, shorter than the header", bytes.len())));
        }
        let mut cur = Cursor { bytes: &bytes, at: 12 };
        let config = TsdfConfig {
            voxel_size_m: cur.f32()?,
            trunc_voxels: cur.f32()?,
            depth_min_m: cur.f32()?,
            depth_max_m: cur.f32()?,
            weight_cap: {
                let has = cur.u8()?;
                let cap = cur.f32()?;
                (has != 0).then_some(cap)
            },
            weight_threshold: 1.0,
        };
        let next_order = if version == 1 { None } else { Some(cur.u64()?) };
        let count = cur.u64()?;
        let expected = (count as u128) * block_bytes as u128 + header_bytes as u128 + 4;
        if (bytes.len() as u128) < expected {
            return Err(MapError::Truncated(format!("{} bytes for {count} blocks (expected {expected})", bytes.len())));
        }
        let body = bytes.len() - 4;
        let stored = u32::from_le_bytes([bytes[body], bytes[body + 1], bytes[body + 2], bytes[body + 3]]);
        let computed = crc32fast::hash(&bytes[..body]);
        if stored != computed {
            return Err(MapError::ChecksumMismatch { stored, computed });
        }
        if (bytes.len() as u128) != expected {
            return Err(MapError::Truncated(format!(
                "{} bytes for {count} blocks (expected {expected}): trailing data",
                bytes.len()
            )));
        }
        config.validate()?;
        let mut map = TsdfMap::new(config);
        for i in 0..count {
            let key = IVec3::new(cur.i32()?, cur.i32()?, cur.i32()?);
            if key.to_array().iter().any(|v| v.unsigned_abs() > MAX_BLOCK_KEY as u32) {
                return Err(MapError::InvalidContent(format!("block key {key} outside +-{MAX_BLOCK_KEY}")));
            }
            // version 1: allocation order is key order
            let order = if next_order.is_some() { cur.u64()? } else { i };
            if next_order.is_some_and(|n| order >= n) {
                return Err(MapError::InvalidContent(format!(
                    "block {key}: allocation order {order} not below the map's next ({})",
                    next_order.unwrap_or(0)
                )));
            }
            let (id, new) = map.allocate(key);
            if !new {
                return Err(MapError::Truncated(format!("duplicate block key {key}")));
            }
            let mut block = Block::default();
            for i in 0..BLOCK_VOXELS {
                let (tsdf, weight) = (cur.f32()?, cur.f32()?);
                let colour = [cur.f32()?, cur.f32()?, cur.f32()?];
                if !(tsdf.is_finite() && weight.is_finite() && colour.iter().all(|c| c.is_finite())) {
                    return Err(MapError::InvalidContent(format!("block {key}, voxel {i}: non-finite value")));
                }
                block.set_voxel(i, Voxel { tsdf, weight, colour });
            }
            *map.layer.block_mut(id) = block;
            map.order[id as usize] = order;
            map.refresh_sign_flags(id);
            map.mark_dirty(id);
        }
        map.next_order = next_order.unwrap_or(count);
        let mut orders = map.order.clone();
        orders.sort_unstable();
        if let Some(w) = orders.windows(2).find(|w| w[0] == w[1]) {
            return Err(MapError::InvalidContent(format!("two blocks share allocation order {}", w[0])));
        }
        Ok(map)
    }
}

fn bad_magic(bytes: &[u8]) -> MapError {
    MapError::BadMagic { found: bytes[..bytes.len().min(8)].to_vec(), expected: MAGIC.to_vec() }
}

/// A writer that keeps the CRC-32 of what passes through it.
struct Crc32Writer<'a, W: Write> {
    w: &'a mut W,
    crc: crc32fast::Hasher,
}

impl<W: Write> Crc32Writer<'_, W> {
    fn write_all(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.crc.update(bytes);
        self.w.write_all(bytes)
    }
}

struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Cursor<'_> {
    fn take<const N: usize>(&mut self) -> Result<[u8; N], MapError> {
        let s = self
            .bytes
            .get(self.at..self.at + N)
            .ok_or_else(|| MapError::Truncated(format!("stream ends at byte {}", self.bytes.len())))?;
        self.at += N;
        let mut out = [0u8; N];
        out.copy_from_slice(s);
        Ok(out)
    }
    fn u8(&mut self) -> Result<u8, MapError> {
        Ok(self.take::<1>()?[0])
    }
    fn f32(&mut self) -> Result<f32, MapError> {
        Ok(f32::from_le_bytes(self.take()?))
    }
    fn i32(&mut self) -> Result<i32, MapError> {
        Ok(i32::from_le_bytes(self.take()?))
    }
    fn u64(&mut self) -> Result<u64, MapError> {
        Ok(u64::from_le_bytes(self.take()?))
    }
}
