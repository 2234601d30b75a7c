//! Named parameter access: deterministic initialisation, export/import by state-dict path, and
//! safetensors files (f32 or f16).
//!
//! Paths are the module field names joined by `.` (`encoder.down.0.block.1.conv1.weight`), equal
//! to the authors' Lightning state-dict keys for the `paper` preset. Parameter ids are derived from
//! the path (FNV-1a), so optimizer state saved by one process applies to the same parameter in
//! another.

use std::collections::BTreeMap;
use std::path::Path;

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::tensor::{Tensor, TensorData};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::ModelError;

/// One exported parameter: shape and row-major f32 values.
#[derive(Debug, Clone, PartialEq)]
pub struct NamedTensor {
    /// Tensor shape (PyTorch layout: conv weights `[out, in, kh, kw]`).
    pub shape: Vec<usize>,
    /// Row-major values.
    pub values: Vec<f32>,
}

/// FNV-1a hash of a parameter path: its stable [`ParamId`].
pub fn param_id_for_path(path: &str) -> ParamId {
    let mut h: u64 = 0xcbf29ce484222325;
    for b in path.bytes() {
        h ^= b as u64;
        h = h.wrapping_mul(0x100000001b3);
    }
    ParamId::from(h)
}

/// Sees each float parameter of a module with its path (in [`WithPath`]), and may replace it.
trait NamedMapper {
    fn map_named<const D: usize>(&mut self, path: &str, param: Param<Tensor<D>>) -> Param<Tensor<D>>;
}

/// Sees each float parameter of a module with its path (in [`WithPath`]).
trait NamedVisitor {
    fn visit_named<const D: usize>(&mut self, path: &str, param: &Param<Tensor<D>>);
}

/// The one traversal that names parameters: tracks the module path (field names joined by `.`)
/// and hands each float parameter with its path to `inner`.
struct WithPath<T> {
    stack: Vec<String>,
    inner: T,
}

impl<T> WithPath<T> {
    fn new(inner: T) -> Self {
        Self { stack: Vec::new(), inner }
    }
}

impl<T: NamedMapper> ModuleMapper for WithPath<T> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.stack.push(name.to_string());
    }
    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.stack.pop();
    }
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let path = self.stack.join(".");
        self.inner.map_named(&path, param)
    }
}

impl<T: NamedVisitor> ModuleVisitor for WithPath<T> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.stack.push(name.to_string());
    }
    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.stack.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let path = self.stack.join(".");
        self.inner.visit_named(&path, param);
    }
}

fn tensor_to_vec<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    t.to_data().try_to_vec_as::<f32>().unwrap_or_default()
}

/// Re-initialises every float parameter deterministically from `seed` and assigns path-derived ids.
pub(crate) fn init_params<M: Module>(module: M, seed: u64) -> M {
    struct Init {
        seed: u64,
        last_fan_in: usize,
    }
    impl NamedMapper for Init {
        fn map_named<const D: usize>(&mut self, path: &str, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
            let id = param_id_for_path(path);
            let (_, old, mapper) = param.consume();
            let shape = old.dims();
            let n: usize = shape.iter().product();
            let parts: Vec<&str> = path.split('.').collect();
            let leaf = parts.last().copied().unwrap_or("");
            let parent = if parts.len() >= 2 { parts[parts.len() - 2] } else { "" };
            let mut rng = ChaCha8Rng::seed_from_u64(self.seed ^ id.val().rotate_left(17));
            let values: Vec<f32> = if parent.starts_with("norm") || leaf == "gamma" || leaf == "beta" {
                let one = leaf == "weight" || leaf == "gamma";
                vec![if one { 1.0 } else { 0.0 }; n]
            } else if path == "conv_in.weight" && shape.len() == 4 {
                // Mask fusion: identity on the 4 data channels, zero on the mask channel.
                let i = shape[1];
                (0..n).map(|k| if k / i == k % i { 1.0 } else { 0.0 }).collect()
            } else if path == "conv_in.bias" {
                vec![0.0; n]
            } else if path.ends_with("embedding.weight") && shape.len() == 2 {
                let b = 1.0 / shape[0] as f32;
                (0..n).map(|_| rng.random_range(-b..b)).collect()
            } else {
                // PyTorch default conv init: U(±1/sqrt(fan_in)) for weight and bias.
                let fan_in: usize = if leaf == "bias" { self.last_fan_in } else { shape[1..].iter().product() };
                self.last_fan_in = fan_in;
                let b = 1.0 / (fan_in.max(1) as f32).sqrt();
                (0..n).map(|_| rng.random_range(-b..b)).collect()
            };
            let new = Tensor::<D>::from_data(TensorData::new(values, shape), &old.device());
            Param::from_mapped_value(id, new, mapper)
        }
    }
    module.map(&mut WithPath::new(Init { seed, last_fan_in: 1 }))
}

/// Exports every float parameter by path, sorted by path.
pub fn named_tensors<M: Module>(module: &M) -> BTreeMap<String, NamedTensor> {
    struct Export {
        out: BTreeMap<String, NamedTensor>,
    }
    impl NamedVisitor for Export {
        fn visit_named<const D: usize>(&mut self, path: &str, param: &Param<Tensor<D>>) {
            let t = param.val();
            let shape = t.dims().to_vec();
            self.out.insert(path.to_string(), NamedTensor { shape, values: tensor_to_vec(&t) });
        }
    }
    let mut v = WithPath::new(Export { out: BTreeMap::new() });
    module.visit(&mut v);
    v.inner.out
}

/// Number of scalar parameters of a module.
pub fn parameter_count<M: Module>(module: &M) -> usize {
    module.num_params()
}

/// Replaces parameters by path from `tensors`. Every module parameter must be present with the same
/// shape unless `allow_missing`; names in `tensors` the module lacks are errors unless `allow_unused`.
/// A parameter with a non-finite value (NaN, +-inf) is an error: this is the one place weights
/// enter a model (weight files, converted checkpoints, resumed training, codebook updates).
pub fn load_named<M: Module>(
    module: M,
    tensors: &BTreeMap<String, NamedTensor>,
    allow_missing: bool,
    allow_unused: bool,
) -> Result<M, ModelError> {
    struct Import<'a> {
        tensors: &'a BTreeMap<String, NamedTensor>,
        used: Vec<String>,
        errors: Vec<String>,
        allow_missing: bool,
    }
    impl NamedMapper for Import<'_> {
        fn map_named<const D: usize>(&mut self, path: &str, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
            let Some(src) = self.tensors.get(path) else {
                if !self.allow_missing {
                    self.errors.push(format!("missing parameter {path}"));
                }
                return param;
            };
            self.used.push(path.to_string());
            let (id, old, mapper) = param.consume();
            let shape = old.dims();
            let n: usize = shape.iter().product();
            let same = src.shape.iter().product::<usize>() == n && src.values.len() == n && {
                let squeezed = |s: &[usize]| s.iter().copied().filter(|&d| d != 1).collect::<Vec<_>>();
                squeezed(&src.shape) == squeezed(&shape)
            };
            if !same {
                self.errors.push(format!("parameter {path}: shape {:?} in file, {:?} in model", src.shape, shape));
                return Param::from_mapped_value(id, old, mapper);
            }
            if let Some(bad) = first_non_finite(&src.values) {
                self.errors.push(format!("parameter {path}: {bad}"));
                return Param::from_mapped_value(id, old, mapper);
            }
            let new = Tensor::<D>::from_data(TensorData::new(src.values.clone(), shape), &old.device());
            // keep the parameter trainable when it was (loading into a model under training)
            let new = if old.is_require_grad() { new.require_grad() } else { new };
            Param::from_mapped_value(id, new, mapper)
        }
    }
    let mut w = WithPath::new(Import { tensors, used: Vec::new(), errors: Vec::new(), allow_missing });
    let module = module.map(&mut w);
    let m = &mut w.inner;
    if !allow_unused {
        for name in tensors.keys() {
            if !m.used.contains(name) {
                m.errors.push(format!("unused tensor {name}"));
            }
        }
    }
    if m.errors.is_empty() {
        Ok(module)
    } else {
        let n = m.errors.len();
        m.errors.truncate(8);
        if n > m.errors.len() {
            let more = n - m.errors.len();
            m.errors.push(format!("and {more} more"));
        }
        Err(ModelError::WeightsMismatch { problems: std::mem::take(&mut m.errors) })
    }
}

/// Storage precision of a safetensors weight file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum WeightPrecision {
    /// 32-bit floats.
    F32,
    /// 16-bit floats (half the size; used for the shipped model).
    F16,
}

/// Largest finite f16 value: [`WeightPrecision::F16`] refuses tensors with larger magnitudes.
pub const F16_MAX: f32 = 65504.0;

/// The first non-finite value of `values`, described (`"NaN at index 3 (of 12)"`).
pub fn first_non_finite(values: &[f32]) -> Option<String> {
    let (i, v) = values.iter().enumerate().find(|(_, v)| !v.is_finite())?;
    let n = values.iter().filter(|v| !v.is_finite()).count();
    Some(format!("{v} at index {i} ({n} non-finite of {} values)", values.len()))
}

/// Serialises named tensors to safetensors bytes, with `metadata` (e.g. the model config JSON).
/// Errors on a non-finite value (a diverged model is never written) and, for
/// [`WeightPrecision::F16`], on a magnitude above [`F16_MAX`] (it would become infinite).
pub fn to_safetensors_bytes(
    tensors: &BTreeMap<String, NamedTensor>,
    precision: WeightPrecision,
    metadata: Option<std::collections::HashMap<String, String>>,
) -> Result<Vec<u8>, ModelError> {
    use safetensors::tensor::{Dtype, TensorView};
    let mut buffers: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::with_capacity(tensors.len());
    for (name, t) in tensors {
        if let Some(bad) = first_non_finite(&t.values) {
            return Err(ModelError::Unwritable { name: name.clone(), problem: bad });
        }
        let bytes: Vec<u8> = match precision {
            WeightPrecision::F32 => t.values.iter().flat_map(|v| v.to_le_bytes()).collect(),
            WeightPrecision::F16 => {
                if let Some((i, v)) = t.values.iter().enumerate().find(|(_, v)| v.abs() > F16_MAX) {
                    return Err(ModelError::Unwritable {
                        name: name.clone(),
                        problem: format!(
                            "value {v} at index {i} overflows f16 (largest finite {F16_MAX}); keep 32-bit floats"
                        ),
                    });
                }
                t.values.iter().flat_map(|v| half::f16::from_f32(*v).to_le_bytes()).collect()
            }
        };
        buffers.push((name.clone(), t.shape.clone(), bytes));
    }
    let dtype = match precision {
        WeightPrecision::F32 => Dtype::F32,
        WeightPrecision::F16 => Dtype::F16,
    };
    let mut views = Vec::with_capacity(buffers.len());
    for (name, shape, bytes) in &buffers {
        let view = TensorView::new(dtype, shape.clone(), bytes)
            .map_err(|e| ModelError::Unwritable { name: name.clone(), problem: e.to_string() })?;
        views.push((name.clone(), view));
    }
    safetensors::serialize(views, metadata).map_err(|e| ModelError::state("safetensors", e))
}

/// Named tensors by path (sorted).
pub type TensorMap = BTreeMap<String, NamedTensor>;

/// Parses safetensors bytes (F32, F16 or BF16 tensors) into named f32 tensors plus metadata.
pub fn from_safetensors_bytes(bytes: &[u8]) -> Result<(TensorMap, BTreeMap<String, String>), ModelError> {
    use safetensors::tensor::Dtype;
    let st = safetensors::SafeTensors::deserialize(bytes)
        .map_err(|e| ModelError::Format { what: "safetensors", msg: e.to_string() })?;
    let mut out = BTreeMap::new();
    for (name, view) in st.tensors() {
        let data = view.data();
        let values: Vec<f32> = match view.dtype() {
            Dtype::F32 => data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect(),
            Dtype::F16 => data.chunks_exact(2).map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32()).collect(),
            Dtype::BF16 => data.chunks_exact(2).map(|c| half::bf16::from_le_bytes([c[0], c[1]]).to_f32()).collect(),
            other => {
                return Err(ModelError::Format {
                    what: "a safetensors tensor",
                    msg: format!("{name}: unsupported dtype {other:?}"),
                })
            }
        };
        out.insert(name, NamedTensor { shape: view.shape().to_vec(), values });
    }
    let (_, meta) = safetensors::SafeTensors::read_metadata(bytes)
        .map_err(|e| ModelError::Format { what: "a safetensors header", msg: e.to_string() })?;
    let metadata: BTreeMap<String, String> = meta.metadata().clone().unwrap_or_default().into_iter().collect();
    Ok((out, metadata))
}

/// Writes a module's parameters to a safetensors file atomically (temp file + rename).
pub fn save_safetensors<M: Module>(
    module: &M,
    path: &Path,
    precision: WeightPrecision,
    metadata: Option<std::collections::HashMap<String, String>>,
) -> Result<(), ModelError> {
    let bytes = to_safetensors_bytes(&named_tensors(module), precision, metadata)?;
    write_atomic(path, &bytes)
}

/// Writes `bytes` to `path` atomically with [`sgam_io::write_atomic`] (a uniquely named
/// temporary sibling, fsynced, renamed; removed on failure); errors name `path`.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ModelError> {
    Ok(sgam_io::write_atomic(path, |w| std::io::Write::write_all(w, bytes))?)
}
