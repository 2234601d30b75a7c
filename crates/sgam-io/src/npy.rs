//! A small reader/writer for NumPy `.npy` files (format versions 1.0, 2.0 and 3.0).
//!
//! Hand-written because the format is tiny (magic, a Python-literal header dict, raw values) and
//! we need only floating-point arrays; this keeps error messages ours (they name the file).

use std::io::Write;
use std::path::Path;

use sgam_core::Image;

use crate::{write_atomic, IoError};

const MAGIC: &[u8; 6] = b"\x93NUMPY";

#[derive(Debug, Clone, Copy, PartialEq)]
enum Dtype {
    F16,
    F32,
    F64,
}

impl Dtype {
    fn size(self) -> usize {
        match self {
            Dtype::F16 => 2,
            Dtype::F32 => 4,
            Dtype::F64 => 8,
        }
    }
}

/// The parsed header of an `.npy` file and where its data starts.
#[derive(Debug)]
struct Header {
    dtype: Dtype,
    big_endian: bool,
    fortran_order: bool,
    shape: Vec<usize>,
    data_offset: usize,
}

fn parse_header(path: &Path, bytes: &[u8]) -> Result<Header, IoError> {
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err(IoError::format(path, "not an .npy file (missing \\x93NUMPY magic)"));
    }
    let major = bytes[6];
    let (header_len, start): (usize, usize) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(IoError::format(path, "truncated .npy header"));
            }
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => return Err(IoError::format(path, format!("unsupported .npy format version {v}"))),
    };
    let end = start
        .checked_add(header_len)
        .filter(|e| *e <= bytes.len())
        .ok_or_else(|| IoError::format(path, "truncated .npy header"))?;
    let text =
        std::str::from_utf8(&bytes[start..end]).map_err(|_| IoError::format(path, "the .npy header is not text"))?;

    let descr = dict_value(text, "descr").ok_or_else(|| IoError::format(path, "the .npy header has no 'descr'"))?;
    let descr = descr.trim().trim_matches(|c| c == '\'' || c == '"');
    let (big_endian, code) = match descr.split_at_checked(1) {
        Some(("<", c)) | Some(("|", c)) | Some(("=", c)) => (false, c),
        Some((">", c)) => (true, c),
        _ => (false, descr),
    };
    let dtype = match code {
        "f2" => Dtype::F16,
        "f4" => Dtype::F32,
        "f8" => Dtype::F64,
        _ => {
            return Err(IoError::format(
                path,
                format!("unsupported .npy dtype '{descr}' (supported: float16, float32, float64)"),
            ))
        }
    };
    let fortran = dict_value(text, "fortran_order")
        .ok_or_else(|| IoError::format(path, "the .npy header has no 'fortran_order'"))?;
    let fortran_order = match fortran.trim() {
        "True" => true,
        "False" => false,
        other => return Err(IoError::format(path, format!("bad fortran_order '{other}' in the .npy header"))),
    };
    let shape_text =
        dict_value(text, "shape").ok_or_else(|| IoError::format(path, "the .npy header has no 'shape'"))?;
    let inner = shape_text
        .trim()
        .strip_prefix('(')
        .and_then(|s| s.strip_suffix(')'))
        .ok_or_else(|| IoError::format(path, format!("bad shape '{shape_text}' in the .npy header")))?;
    let shape = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.trim_end_matches('L').parse::<usize>())
        .collect::<Result<Vec<_>, _>>()
        .map_err(|_| IoError::format(path, format!("bad shape '{shape_text}' in the .npy header")))?;
    Ok(Header { dtype, big_endian, fortran_order, shape, data_offset: end })
}

/// The raw text of the value of `key` in a Python dict literal (`{'key': value, ...}`).
fn dict_value<'a>(text: &'a str, key: &str) -> Option<&'a str> {
    let pos = text.find(&format!("'{key}'")).or_else(|| text.find(&format!("\"{key}\"")))?;
    let rest = &text[pos + key.len() + 2..];
    let rest = rest.trim_start().strip_prefix(':')?.trim_start();
    // The value ends at the first comma outside parentheses / quotes, or at the closing brace.
    let mut depth = 0i32;
    let mut quote: Option<char> = None;
    for (i, c) in rest.char_indices() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), _) => {}
            (None, '\'' | '"') => quote = Some(c),
            (None, '(') => depth += 1,
            (None, ')') => depth -= 1,
            (None, ',') if depth == 0 => return Some(&rest[..i]),
            (None, '}') if depth == 0 => return Some(&rest[..i]),
            _ => {}
        }
    }
    None
}

/// Decodes the values in C (row-major) order.
fn decode<T>(path: &Path, bytes: &[u8], conv: impl Fn(f64) -> T) -> Result<(Vec<usize>, Vec<T>), IoError> {
    let h = parse_header(path, bytes)?;
    let count = h
        .shape
        .iter()
        .try_fold(1usize, |acc, d| acc.checked_mul(*d))
        .ok_or_else(|| IoError::format(path, format!("shape {:?} is too large", h.shape)))?;
    let need = count
        .checked_mul(h.dtype.size())
        .ok_or_else(|| IoError::format(path, format!("shape {:?} is too large", h.shape)))?;
    let have = bytes.len() - h.data_offset;
    if have < need {
        return Err(IoError::format(
            path,
            format!("truncated .npy: shape {:?} needs {need} bytes of data, found {have}", h.shape),
        ));
    }
    if have > need {
        return Err(IoError::format(
            path,
            format!("corrupt .npy: {} unexpected trailing bytes after the data of shape {:?}", have - need, h.shape),
        ));
    }
    let data = &bytes[h.data_offset..];
    let size = h.dtype.size();
    let big = h.big_endian;
    let values: Vec<T> = data
        .chunks_exact(size)
        .map(|c| {
            let v = match h.dtype {
                Dtype::F16 => {
                    let b = [c[0], c[1]];
                    half::f16::from_bits(if big { u16::from_be_bytes(b) } else { u16::from_le_bytes(b) }).to_f64()
                }
                Dtype::F32 => {
                    let b = [c[0], c[1], c[2], c[3]];
                    (if big { f32::from_be_bytes(b) } else { f32::from_le_bytes(b) }) as f64
                }
                Dtype::F64 => {
                    let b = [c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]];
                    if big {
                        f64::from_be_bytes(b)
                    } else {
                        f64::from_le_bytes(b)
                    }
                }
            };
            conv(v)
        })
        .collect();
    let values = if h.fortran_order && h.shape.len() > 1 { fortran_to_c(&h.shape, values) } else { values };
    Ok((h.shape, values))
}

/// Reorders column-major (Fortran) values to row-major (C) order.
fn fortran_to_c<T>(shape: &[usize], values: Vec<T>) -> Vec<T> {
    let n = values.len();
    let mut slots: Vec<Option<T>> = values.into_iter().map(Some).collect();
    let mut out = Vec::with_capacity(n);
    let mut index = vec![0usize; shape.len()];
    for _ in 0..n {
        // Fortran offset of the current C-order multi-index.
        let mut offset = 0usize;
        let mut stride = 1usize;
        for (i, d) in index.iter().zip(shape) {
            offset += i * stride;
            stride *= d;
        }
        if let Some(v) = slots[offset].take() {
            out.push(v);
        }
        // Advance the C-order multi-index (last axis fastest).
        for k in (0..shape.len()).rev() {
            index[k] += 1;
            if index[k] < shape[k] {
                break;
            }
            index[k] = 0;
        }
    }
    out
}

fn read_bytes(path: &Path) -> Result<Vec<u8>, IoError> {
    std::fs::read(path).map_err(|e| IoError::io(path, e))
}

/// Reads a 2-D floating-point array as an image (`shape (H, W)`, or `(H, W, 1)`).
/// float16/float32/float64, either byte order; Fortran-ordered arrays are transposed to
/// row-major. Values are returned as stored (no validity interpretation).
pub fn read_npy_f32(path: &Path) -> Result<Image<f32>, IoError> {
    let bytes = read_bytes(path)?;
    let (shape, data) = decode(path, &bytes, |v| v as f32)?;
    let (h, w) = match shape.as_slice() {
        [h, w] | [h, w, 1] => (*h, *w),
        _ => {
            return Err(IoError::format(
                path,
                format!("expected a 2-D array (H, W) or (H, W, 1), found shape {shape:?}"),
            ))
        }
    };
    if h == 0 || w == 0 || h > u32::MAX as usize || w > u32::MAX as usize {
        return Err(IoError::format(path, format!("unusable image shape {shape:?}")));
    }
    Ok(Image { width: w as u32, height: h as u32, data })
}

/// Reads a small floating-point array of any shape (e.g. a 3x3 `K_00000.npy`, a `(3,)`
/// translation) as `(values in C order, shape)`.
pub fn read_npy_matrix(path: &Path) -> Result<(Vec<f64>, Vec<usize>), IoError> {
    let bytes = read_bytes(path)?;
    let (shape, data) = decode(path, &bytes, |v| v)?;
    Ok((data, shape))
}

/// The `.npy` v1.0 header for a little-endian array of `descr` (e.g. `<f4`) and `shape`, padded
/// with spaces so that the data starts on a 64-byte boundary.
fn header_bytes(descr: &str, shape: &[usize]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_text = if dims.len() == 1 { format!("({},)", dims[0]) } else { format!("({})", dims.join(", ")) };
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_text}, }}");
    let unpadded = MAGIC.len() + 4 + dict.len() + 1;
    dict.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    dict.push('\n');
    let mut out = Vec::with_capacity(10 + dict.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out
}

/// Writes an image as a little-endian float32 `.npy` of shape `(H, W)`, atomically; values are
/// written as given (NaN stays NaN).
pub fn write_npy_f32(path: &Path, img: &Image<f32>) -> Result<(), IoError> {
    if img.data.len() != img.width as usize * img.height as usize {
        return Err(IoError::invalid(
            path,
            format!("cannot write a {}x{} image holding {} values", img.width, img.height, img.data.len()),
        ));
    }
    let header = header_bytes("<f4", &[img.height as usize, img.width as usize]);
    write_atomic(path, |w| {
        w.write_all(&header)?;
        for v in &img.data {
            w.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    })
}

/// Writes a float64 array of any `shape` (C order), atomically.
pub fn write_npy_f64(path: &Path, values: &[f64], shape: &[usize]) -> Result<(), IoError> {
    if shape.iter().product::<usize>() != values.len() {
        return Err(IoError::invalid(path, format!("{} values do not fill shape {shape:?}", values.len())));
    }
    let header = header_bytes("<f8", shape);
    write_atomic(path, |w| {
        w.write_all(&header)?;
        for v in values {
            w.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dict_values_parse() {
        let t = "{'descr': '<f4', 'fortran_order': False, 'shape': (256, 256), }";
        assert_eq!(dict_value(t, "descr"), Some("'<f4'"));
        assert_eq!(dict_value(t, "fortran_order"), Some("False"));
        assert_eq!(dict_value(t, "shape"), Some("(256, 256)"));
        assert_eq!(dict_value(t, "nope"), None);
    }

    #[test]
    fn fortran_reorder_transposes() {
        // 2x3 matrix [[0,1,2],[3,4,5]] stored column-major: 0,3,1,4,2,5
        let c = fortran_to_c(&[2, 3], vec![0, 3, 1, 4, 2, 5]);
        assert_eq!(c, vec![0, 1, 2, 3, 4, 5]);
    }

    #[test]
    fn header_is_aligned() {
        let h = header_bytes("<f4", &[6, 8]);
        assert_eq!(h.len() % 64, 0);
        assert_eq!(*h.last().unwrap(), b'\n');
    }
}
