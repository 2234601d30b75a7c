//! Triangle meshes: PLY (binary write; ASCII/binary read), OBJ and GLB (glTF 2.0 binary) export.

use std::io::Write;
use std::path::Path;

use sgam_core::{srgb_to_linear, TriMesh, Vec3};

use crate::images::to_srgb8;
use crate::{write_atomic, IoError};

fn check_mesh(path: &Path, mesh: &TriMesh) -> Result<(), IoError> {
    if !mesh.colours.is_empty() && mesh.colours.len() != mesh.positions.len() {
        return Err(IoError::invalid(
            path,
            format!("mesh has {} colours for {} vertices", mesh.colours.len(), mesh.positions.len()),
        ));
    }
    let n = mesh.positions.len() as u64;
    if let Some((i, t)) = mesh.triangles.iter().enumerate().find(|(_, t)| t.iter().any(|v| *v as u64 >= n)) {
        return Err(IoError::invalid(path, format!("triangle {i} {t:?} indexes past the {n} vertices")));
    }
    if mesh.positions.len() > u32::MAX as usize {
        return Err(IoError::invalid(path, "too many vertices for 32-bit indices"));
    }
    Ok(())
}

/// Writes `mesh` in the format its extension names: `.ply` (binary, vertex colours), `.obj` or
/// `.glb` (case-insensitive); any other extension is an error naming the path.
pub fn write_mesh(path: &Path, mesh: &TriMesh) -> Result<(), IoError> {
    match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
        Some("ply") => write_ply(path, mesh),
        Some("obj") => write_obj(path, mesh),
        Some("glb") => write_glb(path, mesh),
        _ => Err(IoError::invalid(path, "unknown mesh format (use .ply, .obj or .glb)")),
    }
}

/// Writes a binary little-endian PLY, atomically: `float x y z`, `uchar red green blue` (when
/// the mesh has colours; sRGB rounded to 8 bits), faces as `list uchar int vertex_indices`.
pub fn write_ply(path: &Path, mesh: &TriMesh) -> Result<(), IoError> {
    check_mesh(path, mesh)?;
    let has_colour = !mesh.colours.is_empty();
    write_atomic(path, |w| {
        writeln!(w, "ply\nformat binary_little_endian 1.0\ncomment sgam-rs")?;
        writeln!(w, "element vertex {}", mesh.positions.len())?;
        writeln!(w, "property float x\nproperty float y\nproperty float z")?;
        if has_colour {
            writeln!(w, "property uchar red\nproperty uchar green\nproperty uchar blue")?;
        }
        writeln!(w, "element face {}", mesh.triangles.len())?;
        writeln!(w, "property list uchar int vertex_indices\nend_header")?;
        for (i, p) in mesh.positions.iter().enumerate() {
            for c in p.to_array() {
                w.write_all(&c.to_le_bytes())?;
            }
            if has_colour {
                w.write_all(&mesh.colours[i].map(to_srgb8))?;
            }
        }
        for t in &mesh.triangles {
            w.write_all(&[3u8])?;
            for v in t {
                w.write_all(&(*v as i32).to_le_bytes())?;
            }
        }
        Ok(())
    })
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    /// Scale that maps a stored colour value to `[0, 1]`.
    fn colour_scale(self) -> f64 {
        match self {
            Scalar::U8 | Scalar::I8 => 1.0 / 255.0,
            Scalar::U16 | Scalar::I16 => 1.0 / 65535.0,
            _ => 1.0,
        }
    }
}

#[derive(Debug, Clone)]
enum Property {
    Scalar(String, Scalar),
    List(String, Scalar, Scalar),
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum PlyFormat {
    Ascii,
    BinaryLe,
    BinaryBe,
}

/// Sequential value reader over the body of a PLY file.
struct Body<'a> {
    format: PlyFormat,
    bytes: &'a [u8],
    pos: usize,
}

impl Body<'_> {
    fn next(&mut self, path: &Path, ty: Scalar) -> Result<f64, IoError> {
        if self.format == PlyFormat::Ascii {
            while self.pos < self.bytes.len() && self.bytes[self.pos].is_ascii_whitespace() {
                self.pos += 1;
            }
            let start = self.pos;
            while self.pos < self.bytes.len() && !self.bytes[self.pos].is_ascii_whitespace() {
                self.pos += 1;
            }
            if start == self.pos {
                return Err(IoError::format(path, "truncated PLY: the body ends early"));
            }
            let token = std::str::from_utf8(&self.bytes[start..self.pos]).unwrap_or("?");
            return token.parse::<f64>().map_err(|_| IoError::format(path, format!("PLY: '{token}' is not a number")));
        }
        let n = ty.size();
        let chunk = self
            .bytes
            .get(self.pos..self.pos + n)
            .ok_or_else(|| IoError::format(path, "truncated PLY: the body ends early"))?;
        self.pos += n;
        let mut b = [0u8; 8];
        b[..n].copy_from_slice(chunk);
        if self.format == PlyFormat::BinaryBe {
            b[..n].reverse();
        }
        Ok(match ty {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::F64 => f64::from_le_bytes(b),
        })
    }
}

fn parse_ply_header(path: &Path, bytes: &[u8]) -> Result<(PlyFormat, Vec<Element>, usize), IoError> {
    if !bytes.starts_with(b"ply") {
        return Err(IoError::format(path, "not a PLY file (missing 'ply' magic)"));
    }
    let marker = b"end_header";
    let end = bytes
        .windows(marker.len())
        .position(|w| w == marker)
        .ok_or_else(|| IoError::format(path, "PLY header has no end_header"))?;
    let mut body_start = end + marker.len();
    if bytes.get(body_start) == Some(&b'\r') {
        body_start += 1;
    }
    if bytes.get(body_start) == Some(&b'\n') {
        body_start += 1;
    }
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| IoError::format(path, "PLY header is not text"))?;
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    for (line_no, line) in header.lines().enumerate().skip(1) {
        let words: Vec<&str> = line.split_whitespace().collect();
        let bad = || IoError::format(path, format!("PLY header line {}: '{line}'", line_no + 1));
        match words.as_slice() {
            [] | ["comment", ..] | ["obj_info", ..] => {}
            ["format", f, _] => {
                format = Some(match *f {
                    "ascii" => PlyFormat::Ascii,
                    "binary_little_endian" => PlyFormat::BinaryLe,
                    "binary_big_endian" => PlyFormat::BinaryBe,
                    _ => return Err(bad()),
                })
            }
            ["element", name, count] => elements.push(Element {
                name: name.to_string(),
                count: count.parse().map_err(|_| bad())?,
                properties: Vec::new(),
            }),
            ["property", "list", count_ty, item_ty, name] => {
                let el = elements.last_mut().ok_or_else(bad)?;
                let c = Scalar::parse(count_ty).ok_or_else(bad)?;
                let i = Scalar::parse(item_ty).ok_or_else(bad)?;
                el.properties.push(Property::List(name.to_string(), c, i));
            }
            ["property", ty, name] => {
                let el = elements.last_mut().ok_or_else(bad)?;
                el.properties.push(Property::Scalar(name.to_string(), Scalar::parse(ty).ok_or_else(bad)?));
            }
            _ => return Err(bad()),
        }
    }
    let format = format.ok_or_else(|| IoError::format(path, "PLY header has no format line"))?;
    Ok((format, elements, body_start))
}

/// Reads a PLY mesh (ASCII, binary little- or big-endian): vertex `x y z` (any numeric type),
/// optional colour `red green blue` (or `r g b`; 8-bit, 16-bit or float in `[0, 1]`), faces from
/// `vertex_indices` / `vertex_index` (polygons are triangulated as fans). Other properties and
/// elements (normals, alpha, edges, ...) are skipped. Indices past the vertex count, non-finite
/// positions (also f64 values beyond the f32 range), truncated bodies and malformed headers are
/// errors.
pub fn read_ply(path: &Path) -> Result<TriMesh, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, e))?;
    let (format, elements, body_start) = parse_ply_header(path, &bytes)?;
    let mut body = Body { format, bytes: &bytes[body_start..], pos: 0 };
    let mut mesh = TriMesh::default();
    // Bound pre-allocation by what the file could hold, so a lying header cannot exhaust memory.
    let cap = |count: usize| count.min(bytes.len());
    for el in &elements {
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        let find = |names: &[&str]| {
            el.properties.iter().position(|p| matches!(p, Property::Scalar(n, _) if names.contains(&n.as_str())))
        };
        let (xi, yi, zi) = (find(&["x"]), find(&["y"]), find(&["z"]));
        let (ri, gi, bi) = (
            find(&["red", "r", "diffuse_red"]),
            find(&["green", "g", "diffuse_green"]),
            find(&["blue", "b", "diffuse_blue"]),
        );
        if is_vertex && (xi.is_none() || yi.is_none() || zi.is_none()) {
            return Err(IoError::format(path, "PLY vertex element has no x, y, z properties"));
        }
        let has_colour = is_vertex && ri.is_some() && gi.is_some() && bi.is_some();
        let face_list = el
            .properties
            .iter()
            .position(|p| matches!(p, Property::List(n, _, _) if n == "vertex_indices" || n == "vertex_index"));
        if is_vertex {
            mesh.positions.reserve(cap(el.count));
            if has_colour {
                mesh.colours.reserve(cap(el.count));
            }
        }
        let mut values = vec![0.0f64; el.properties.len()];
        let mut scales = vec![1.0f64; el.properties.len()];
        let mut polygon: Vec<u32> = Vec::new();
        for _ in 0..el.count {
            for (pi, prop) in el.properties.iter().enumerate() {
                match prop {
                    Property::Scalar(_, ty) => {
                        values[pi] = body.next(path, *ty)?;
                        scales[pi] = ty.colour_scale();
                    }
                    Property::List(_, count_ty, item_ty) => {
                        let n = body.next(path, *count_ty)?;
                        if !(0.0..=1e6).contains(&n) || n.fract() != 0.0 {
                            return Err(IoError::format(path, format!("PLY: bad list length {n}")));
                        }
                        let keep = is_face && Some(pi) == face_list;
                        polygon.clear();
                        for _ in 0..n as usize {
                            let v = body.next(path, *item_ty)?;
                            if keep {
                                if !(0.0..u32::MAX as f64).contains(&v) || v.fract() != 0.0 {
                                    return Err(IoError::format(path, format!("PLY: bad vertex index {v}")));
                                }
                                polygon.push(v as u32);
                            }
                        }
                        if keep {
                            for k in 1..polygon.len().saturating_sub(1) {
                                mesh.triangles.push([polygon[0], polygon[k], polygon[k + 1]]);
                            }
                        }
                    }
                }
            }
            if is_vertex {
                let g = |i: Option<usize>| i.map(|i| values[i]).unwrap_or(0.0);
                let p = Vec3::new(g(xi) as f32, g(yi) as f32, g(zi) as f32);
                if !p.is_finite() {
                    return Err(IoError::invalid(
                        path,
                        format!("PLY vertex {} has a non-finite position {p}", mesh.positions.len()),
                    ));
                }
                mesh.positions.push(p);
                if has_colour {
                    let c = |i: Option<usize>| i.map(|i| (values[i] * scales[i]) as f32).unwrap_or(0.0);
                    mesh.colours.push([c(ri), c(gi), c(bi)]);
                }
            }
        }
    }
    let n = mesh.positions.len() as u64;
    if let Some(t) = mesh.triangles.iter().find(|t| t.iter().any(|v| *v as u64 >= n)) {
        return Err(IoError::format(path, format!("PLY face {t:?} indexes past the {n} vertices")));
    }
    Ok(mesh)
}

/// Writes a Wavefront OBJ, atomically: `v x y z r g b` (colour in `[0, 1]` when the mesh has
/// colours) and `f a b c` (1-based).
pub fn write_obj(path: &Path, mesh: &TriMesh) -> Result<(), IoError> {
    check_mesh(path, mesh)?;
    write_atomic(path, |w| {
        writeln!(w, "# sgam-rs mesh: {} vertices, {} triangles", mesh.positions.len(), mesh.triangles.len())?;
        for (i, p) in mesh.positions.iter().enumerate() {
            match mesh.colours.get(i) {
                Some(c) => writeln!(w, "v {} {} {} {} {} {}", p.x, p.y, p.z, c[0], c[1], c[2])?,
                None => writeln!(w, "v {} {} {}", p.x, p.y, p.z)?,
            }
        }
        for t in &mesh.triangles {
            writeln!(w, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
        }
        Ok(())
    })
}

/// World (+z up) to glTF (+y up) axes: `(x, y, z)_gltf = (x, z, -y)_world`, a proper rotation
/// (-90 degrees about x), so triangle winding and handedness are preserved.
pub fn world_to_gltf(p: Vec3) -> Vec3 {
    Vec3::new(p.x, p.z, -p.y)
}

const GLB_MAGIC: u32 = 0x4654_6C67; // "glTF"
const CHUNK_JSON: u32 = 0x4E4F_534A; // "JSON"
const CHUNK_BIN: u32 = 0x004E_4942; // "BIN\0"
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;

/// Writes a glTF 2.0 binary (`.glb`), atomically: one node, one mesh, one triangle primitive
/// with `POSITION` (float VEC3 with min/max), `COLOR_0` (float VEC3, *linear* RGB converted from
/// our sRGB, when the mesh has colours) and u32 indices, and a rough, non-metallic, double-sided
/// white material. Axes are converted from our world (+z up) to glTF's (+y up, right handed):
/// `(x, y, z)_gltf = (x, z, -y)_world` ([`world_to_gltf`]); units stay metres. An empty mesh gives
/// a valid file with an empty scene. Non-finite positions are errors.
pub fn write_glb(path: &Path, mesh: &TriMesh) -> Result<(), IoError> {
    check_mesh(path, mesh)?;
    if let Some(i) = mesh.positions.iter().position(|p| !p.is_finite()) {
        return Err(IoError::invalid(path, format!("vertex {i} is not finite: {}", mesh.positions[i])));
    }
    let asset = serde_json::json!({"version": "2.0", "generator": "sgam-rs"});
    let empty = mesh.positions.is_empty() || mesh.triangles.is_empty();
    let (json, bin) = if empty {
        (serde_json::json!({"asset": asset, "scene": 0, "scenes": [{"nodes": []}]}), Vec::new())
    } else {
        let positions: Vec<Vec3> = mesh.positions.iter().map(|p| world_to_gltf(*p)).collect();
        let (lo, hi) = positions.iter().fold((positions[0], positions[0]), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
        let mut bin: Vec<u8> = Vec::with_capacity(24 * positions.len() + 12 * mesh.triangles.len());
        for p in &positions {
            bin.extend(p.to_array().iter().flat_map(|c| c.to_le_bytes()));
        }
        let pos_len = bin.len();
        for c in &mesh.colours {
            bin.extend(c.iter().flat_map(|c| srgb_to_linear(*c).to_le_bytes()));
        }
        let col_len = bin.len() - pos_len;
        for t in &mesh.triangles {
            bin.extend(t.iter().flat_map(|v| v.to_le_bytes()));
        }
        let idx_len = bin.len() - pos_len - col_len;
        let n = positions.len();
        let mut attributes = serde_json::json!({"POSITION": 0});
        let mut views =
            vec![serde_json::json!({"buffer": 0, "byteOffset": 0, "byteLength": pos_len, "target": ARRAY_BUFFER})];
        let mut accessors = vec![serde_json::json!({
            "bufferView": 0, "componentType": FLOAT, "count": n, "type": "VEC3",
            "min": lo.to_array(), "max": hi.to_array()
        })];
        if col_len > 0 {
            attributes["COLOR_0"] = serde_json::json!(1);
            views.push(
                serde_json::json!({"buffer": 0, "byteOffset": pos_len, "byteLength": col_len, "target": ARRAY_BUFFER}),
            );
            accessors.push(serde_json::json!({"bufferView": 1, "componentType": FLOAT, "count": n, "type": "VEC3"}));
        }
        let idx_view = views.len();
        views.push(serde_json::json!({
            "buffer": 0, "byteOffset": pos_len + col_len, "byteLength": idx_len, "target": ELEMENT_ARRAY_BUFFER
        }));
        accessors.push(serde_json::json!({
            "bufferView": idx_view, "componentType": UNSIGNED_INT, "count": 3 * mesh.triangles.len(), "type": "SCALAR"
        }));
        let json = serde_json::json!({
            "asset": asset,
            "scene": 0,
            "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0, "name": "world"}],
            "meshes": [{"name": "world", "primitives": [{
                "attributes": attributes, "indices": accessors.len() - 1, "mode": 4, "material": 0
            }]}],
            "materials": [{
                "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0},
                "doubleSided": true
            }],
            "buffers": [{"byteLength": bin.len()}],
            "bufferViews": views,
            "accessors": accessors,
        });
        (json, bin)
    };
    let mut json_bytes = serde_json::to_vec(&json).map_err(|e| IoError::invalid(path, e.to_string()))?;
    while json_bytes.len() % 4 != 0 {
        json_bytes.push(b' ');
    }
    let mut bin = bin;
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json_bytes.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
    if total > u32::MAX as usize {
        return Err(IoError::invalid(path, "mesh too large for a GLB file (4 GiB)"));
    }
    write_atomic(path, |w| {
        w.write_all(&GLB_MAGIC.to_le_bytes())?;
        w.write_all(&2u32.to_le_bytes())?;
        w.write_all(&(total as u32).to_le_bytes())?;
        w.write_all(&(json_bytes.len() as u32).to_le_bytes())?;
        w.write_all(&CHUNK_JSON.to_le_bytes())?;
        w.write_all(&json_bytes)?;
        if !bin.is_empty() {
            w.write_all(&(bin.len() as u32).to_le_bytes())?;
            w.write_all(&CHUNK_BIN.to_le_bytes())?;
            w.write_all(&bin)?;
        }
        Ok(())
    })
}

/// Vertex and triangle counts of a GLB written by `sgam_io::write_glb` (from its JSON chunk).
pub fn glb_counts(path: &Path, glb: &[u8]) -> Result<(u64, u64), IoError> {
    let bad = || IoError::format(path, "not a GLB file");
    if glb.len() < 20 || &glb[0..4] != b"glTF" || &glb[16..20] != b"JSON" {
        return Err(bad());
    }
    // the header's total length: a cut file (an interrupted copy) is refused, not embedded
    let total = u32::from_le_bytes([glb[8], glb[9], glb[10], glb[11]]) as usize;
    if total != glb.len() {
        return Err(IoError::format(
            path,
            format!(
                "a GLB of {} bytes whose header says {total}: the file is cut or damaged (an interrupted copy?)",
                glb.len()
            ),
        ));
    }
    let len = u32::from_le_bytes([glb[12], glb[13], glb[14], glb[15]]) as usize;
    let json: serde_json::Value = serde_json::from_slice(glb.get(20..20 + len).ok_or_else(bad)?)
        .map_err(|e| IoError::format(path, format!("the GLB's JSON chunk: {e}")))?;
    let (mut vertices, mut triangles) = (0, 0);
    for mesh in json["meshes"].as_array().into_iter().flatten() {
        for prim in mesh["primitives"].as_array().into_iter().flatten() {
            let count = |i: &serde_json::Value| {
                i.as_u64().and_then(|i| json["accessors"][i as usize]["count"].as_u64()).unwrap_or(0)
            };
            vertices += count(&prim["attributes"]["POSITION"]);
            triangles += count(&prim["indices"]) / 3;
        }
    }
    Ok((vertices, triangles))
}
