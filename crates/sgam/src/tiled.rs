//! The outputs of a run whose map went partly to tiles (`--max-map-mb`): the world mesh as one
//! glTF per super-block (`mesh-tiles/X_Y_Z.glb`, with `mesh-tiles/index.json`), the single
//! `mesh.ply`/`mesh.glb` when the world has at most `--single-mesh-max-mtri` million triangles, and the
//! overview rendered tile by tile. Memory stays at one tile beside the resident map (and the
//! coarse world).
//!
//! For the viewer, the tiles are grouped into cells of [`CELL_SUPERS`]^3 super-blocks, and the
//! whole world is also written coarse (`mesh-tiles/coarse.glb`, vertex clustering to at most
//! [`COARSE_MAX_TRIANGLES`], each cell's triangles a contiguous range): `world.html` opens on the
//! coarse world and, served, loads the cells near the view in full detail.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use glam::{IVec3, Vec3};
use serde::Serialize;
use sgam_core::{Camera, TriMesh};
use sgam_map::{Rendered, TsdfMap};
use sgam_pipeline::tiles::MapStreaming;

/// The tiles' folder in the run folder.
pub const MESH_TILES_DIR: &str = "mesh-tiles";
/// The coarse world in `mesh-tiles/`.
pub const COARSE_FILE: &str = "coarse.glb";
/// The tiles' index in `mesh-tiles/`.
pub const INDEX_FILE: &str = "index.json";
/// The coarse world (`mesh-tiles/coarse.glb`, what the viewer shows first) has at most this
/// many triangles: its clustering cell doubles until it fits (about 8 MB of glTF).
pub const COARSE_MAX_TRIANGLES: usize = 250_000;
/// Super-blocks per side of a viewer cell: the unit the viewer loads in full detail (4^3
/// super-blocks, 12.8 m at 5 cm voxels).
pub const CELL_SUPERS: i32 = 4;

/// A viewer cell of `mesh-tiles/index.json`: a group of tiles, its triangles in the coarse
/// mesh, and the tiles' files for full detail.
#[derive(Debug, Clone, Serialize)]
pub struct MeshCell {
    /// Cell key (super-block key / [`CELL_SUPERS`], rounded down).
    pub key: [i32; 3],
    /// Bounds of its tiles' vertices, world frame.
    pub min: [f32; 3],
    /// Bounds of its tiles' vertices, world frame.
    pub max: [f32; 3],
    /// Its first triangle in `coarse.glb`.
    pub first: usize,
    /// Its triangles in `coarse.glb`.
    pub count: usize,
    /// Its tiles' files in `mesh-tiles/`.
    pub files: Vec<String>,
    /// Triangles of its tiles in full detail.
    pub triangles: usize,
}

/// One tile of `mesh-tiles/index.json`.
#[derive(Debug, Clone, Serialize)]
pub struct MeshTile {
    /// Super-block key.
    pub key: [i32; 3],
    /// File name in `mesh-tiles/`.
    pub file: String,
    /// Bounds of its vertices, world frame.
    pub min: [f32; 3],
    /// Bounds of its vertices, world frame.
    pub max: [f32; 3],
    /// Vertices.
    pub vertices: usize,
    /// Triangles.
    pub triangles: usize,
}

/// What [`write_mesh_tiles`] wrote.
#[derive(Debug)]
pub struct TiledWorld {
    /// The tiles, by key.
    pub tiles: Vec<MeshTile>,
    /// The viewer's cells, by key.
    pub cells: Vec<MeshCell>,
    /// Triangles of the whole world.
    pub triangles: u64,
    /// The whole world in one mesh (tiles appended, not welded across tiles), when it has at
    /// most the run's `single_mesh_max_triangles`.
    pub single: Option<TriMesh>,
}

impl TiledWorld {
    /// Bounds of the world's vertices.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let mut it = self.tiles.iter().filter(|t| t.vertices > 0);
        let first = it.next()?;
        Some(it.fold((Vec3::from(first.min), Vec3::from(first.max)), |(lo, hi), t| {
            (lo.min(Vec3::from(t.min)), hi.max(Vec3::from(t.max)))
        }))
    }
}

fn tile_name(key: [i32; 3]) -> String {
    let [x, y, z] = key;
    format!("{x}_{y}_{z}.glb")
}

/// Each tile's mesh: the resident map's super-blocks, then the tiles on disk. `each` gets the
/// key and the mesh.
fn for_each_tile_mesh(
    map: &mut TsdfMap,
    streaming: &MapStreaming,
    mut each: impl FnMut([i32; 3], TriMesh) -> Result<()>,
) -> Result<()> {
    for sk in map.super_block_keys() {
        let mesh = map.super_block_mesh(sk);
        each(sk.to_array(), mesh)?;
    }
    for entry in streaming.tiles.entries() {
        let blocks = streaming.tiles.read(entry)?;
        each(entry.key, sgam_map::blocks_mesh(&blocks))?;
    }
    Ok(())
}

/// Writes `dir/mesh-tiles/` (a `.glb` per non-empty tile, `coarse.glb` and `index.json`) for the
/// world of `map` and `streaming`'s tiles; keeps the world as one mesh when it has at most
/// `single_max_triangles`.
pub fn write_mesh_tiles(
    dir: &Path,
    map: &mut TsdfMap,
    streaming: &MapStreaming,
    single_max_triangles: u64,
) -> Result<TiledWorld> {
    let out = dir.join(MESH_TILES_DIR);
    std::fs::create_dir_all(&out).with_context(|| format!("{}: cannot create the folder", out.display()))?;
    let mut tiles = Vec::with_capacity(map.super_block_keys().len() + streaming.tiles.len());
    let mut single = (single_max_triangles > 0).then(TriMesh::default);
    let mut triangles = 0u64;
    let mut coarse_cell_m = 4.0 * map.config().voxel_size_m;
    let mut cells: BTreeMap<[i32; 3], (MeshCell, TriMesh)> = BTreeMap::new();
    for_each_tile_mesh(map, streaming, |key, mesh| {
        let Some((lo, hi)) = mesh.bounds() else { return Ok(()) };
        let file = tile_name(key);
        sgam_io::write_mesh(&out.join(&file), &mesh)?;
        let ckey = IVec3::from_array(key).div_euclid(IVec3::splat(CELL_SUPERS)).to_array();
        let (cell, coarse) = cells.entry(ckey).or_insert_with(|| {
            let empty = MeshCell {
                key: ckey,
                min: lo.to_array(),
                max: hi.to_array(),
                first: 0,
                count: 0,
                files: Vec::new(),
                triangles: 0,
            };
            (empty, TriMesh::default())
        });
        cell.min = Vec3::from(cell.min).min(lo).to_array();
        cell.max = Vec3::from(cell.max).max(hi).to_array();
        cell.files.push(file.clone());
        cell.triangles += mesh.triangles.len();
        coarse.append(&mesh.clustered(coarse_cell_m));
        triangles += mesh.triangles.len() as u64;
        if triangles > single_max_triangles {
            single = None;
        }
        if let Some(s) = &mut single {
            s.append(&mesh);
        }
        tiles.push(MeshTile {
            key,
            file,
            min: lo.to_array(),
            max: hi.to_array(),
            vertices: mesh.positions.len(),
            triangles: mesh.triangles.len(),
        });
        Ok(())
    })?;
    tiles.sort_by_key(|t| t.key);
    // the coarse world: each cell's coarse tiles, coarser until the whole fits the budget
    while cells.values().map(|(_, m)| m.triangles.len()).sum::<usize>() > COARSE_MAX_TRIANGLES {
        coarse_cell_m *= 2.0;
        for (_, m) in cells.values_mut() {
            *m = m.clustered(coarse_cell_m);
        }
    }
    let mut coarse = TriMesh::default();
    let cells: Vec<MeshCell> = cells
        .into_values()
        .map(|(mut cell, m)| {
            cell.first = coarse.triangles.len();
            cell.count = m.triangles.len();
            coarse.append(&m);
            cell
        })
        .collect();
    sgam_io::write_mesh(&out.join(COARSE_FILE), &coarse)?;
    let world = TiledWorld { tiles, cells, triangles, single };
    let (lo, hi) = world.bounds().unwrap_or((Vec3::ZERO, Vec3::ZERO));
    let index = serde_json::json!({
        "format": 1,
        "about": "the world mesh as one glTF per super-block of the map (8^3 blocks); tiles do not overlap",
        "super_block_m": map.config().block_size_m() * 8.0,
        "min": lo.to_array(), "max": hi.to_array(),
        "triangles": world.triangles,
        "coarse": { "file": COARSE_FILE, "cell_m": coarse_cell_m, "triangles": coarse.triangles.len() },
        "cells": world.cells,
        "tiles": world.tiles,
    });
    let bytes = serde_json::to_vec_pretty(&index)?;
    sgam_io::write_atomic(&out.join(INDEX_FILE), |w| std::io::Write::write_all(w, &bytes))?;
    Ok(world)
}

/// The world of `map` and `streaming`'s tiles rendered at `camera` within `[near, far]`: each
/// tile alone, merged by depth.
pub fn rasterize_world(
    map: &TsdfMap,
    streaming: &MapStreaming,
    camera: &Camera,
    near: f32,
    far: f32,
) -> Result<Rendered> {
    let mut out = map.rasterize_range(camera, near, far);
    for entry in streaming.tiles.entries() {
        let (lo, hi) = map.super_block_box(IVec3::from_array(entry.key));
        if !box_in_front(camera, lo, hi, near) {
            continue;
        }
        let tile = TsdfMap::from_evicted(*map.config(), streaming.tiles.read(entry)?)?;
        out.merge_nearer(&tile.rasterize_range(camera, near, far))?;
    }
    Ok(out)
}

/// False when every corner of the box lies behind the camera's near plane.
fn box_in_front(camera: &Camera, lo: Vec3, hi: Vec3, near: f32) -> bool {
    let to_camera = camera.world_from_camera.inverse();
    (0..8).any(|i| {
        let c = Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        );
        to_camera.transform_point(c).z >= near
    })
}
