#![allow(clippy::unwrap_used, clippy::expect_used)]
//! Checkpoint import: the test writes PyTorch zip checkpoints itself (a small pickle writer and a
//! stored zip writer, the layout `torch.save` produces) and converts them with
//! `convert_lightning_checkpoint`, so it needs neither Python nor downloads.

use std::collections::BTreeMap;
use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_model::convert::{convert_lightning_checkpoint, read_lightning_state_dict};
use sgam_model::params::{named_tensors, NamedTensor};
use sgam_model::refiner::load_model;
use sgam_model::{default_device, ModelConfig, ModelError, VqModel};

// ---------------------------------------------------------------------------------------------
// A minimal pickle (protocol 2) writer: only the opcodes torch.save uses for a state dict.
// ---------------------------------------------------------------------------------------------

#[derive(Default)]
struct Pickle(Vec<u8>);

impl Pickle {
    fn proto(&mut self) {
        self.0.extend([0x80, 2]); // PROTO 2
    }
    fn mark(&mut self) {
        self.0.push(b'('); // MARK
    }
    fn tuple(&mut self) {
        self.0.push(b't'); // TUPLE (items since the mark)
    }
    fn empty_tuple(&mut self) {
        self.0.push(b')'); // EMPTY_TUPLE
    }
    fn empty_dict(&mut self) {
        self.0.push(b'}'); // EMPTY_DICT
    }
    fn set_items(&mut self) {
        self.0.push(b'u'); // SETITEMS (key/value pairs since the mark)
    }
    fn reduce(&mut self) {
        self.0.push(b'R'); // REDUCE: callable(*args)
    }
    fn build(&mut self) {
        self.0.push(b'b'); // BUILD: obj.__setstate__(state)
    }
    fn bin_pers_id(&mut self) {
        self.0.push(b'Q'); // BINPERSID: persistent_load(top)
    }
    fn new_false(&mut self) {
        self.0.push(0x89); // NEWFALSE
    }
    fn stop(&mut self) {
        self.0.push(b'.'); // STOP
    }
    fn global(&mut self, module: &str, name: &str) {
        self.0.push(b'c'); // GLOBAL module\nname\n
        self.0.extend(module.as_bytes());
        self.0.push(b'\n');
        self.0.extend(name.as_bytes());
        self.0.push(b'\n');
    }
    fn int(&mut self, v: i32) {
        self.0.push(b'J'); // BININT, 4 bytes little-endian
        self.0.extend(v.to_le_bytes());
    }
    fn str(&mut self, s: &str) {
        self.0.push(b'X'); // BINUNICODE, u32 length + utf-8
        self.0.extend((s.len() as u32).to_le_bytes());
        self.0.extend(s.as_bytes());
    }
    fn int_tuple(&mut self, values: &[usize]) {
        self.mark();
        for &v in values {
            self.int(v as i32);
        }
        self.tuple();
    }
    /// `collections.OrderedDict()`.
    fn ordered_dict(&mut self) {
        self.global("collections", "OrderedDict");
        self.empty_tuple();
        self.reduce();
    }
}

/// How one state-dict entry is stored.
struct Entry {
    name: String,
    /// `FloatStorage`, `HalfStorage`, `LongStorage`, ...
    storage_type: &'static str,
    storage_key: String,
    /// Elements in the whole storage.
    storage_numel: usize,
    /// Element offset of the tensor in its storage.
    offset: usize,
    shape: Vec<usize>,
}

fn contiguous_strides(shape: &[usize]) -> Vec<usize> {
    let mut strides = vec![1; shape.len()];
    for i in (0..shape.len().saturating_sub(1)).rev() {
        strides[i] = strides[i + 1] * shape[i + 1];
    }
    strides
}

/// `torch._utils._rebuild_tensor_v2(persistent_load(('storage', torch.<T>Storage, key, 'cpu',
/// numel)), offset, size, stride, False, OrderedDict())`.
fn write_tensor(p: &mut Pickle, e: &Entry) {
    p.global("torch._utils", "_rebuild_tensor_v2");
    p.mark();
    p.mark();
    p.str("storage");
    p.global("torch", e.storage_type);
    p.str(&e.storage_key);
    p.str("cpu");
    p.int(e.storage_numel as i32);
    p.tuple();
    p.bin_pers_id();
    p.int(e.offset as i32);
    p.int_tuple(&e.shape);
    p.int_tuple(&contiguous_strides(&e.shape));
    p.new_false();
    p.ordered_dict();
    p.tuple();
    p.reduce();
}

/// The state dict as torch pickles it: an `OrderedDict` filled by SETITEMS, then BUILD with its
/// `_metadata` attribute (a dict of per-module versions, no tensors).
fn write_state_dict(p: &mut Pickle, entries: &[Entry]) {
    p.ordered_dict();
    p.mark();
    for e in entries {
        p.str(&e.name);
        write_tensor(p, e);
    }
    p.set_items();
    p.empty_dict();
    p.mark();
    p.str("_metadata");
    p.ordered_dict();
    p.mark();
    p.str("");
    p.empty_dict();
    p.mark();
    p.str("version");
    p.int(1);
    p.set_items();
    p.set_items();
    p.set_items();
    p.build();
}

/// A Lightning checkpoint pickle: `{"epoch", "global_step", "pytorch-lightning_version",
/// "state_dict"}`.
fn lightning_pickle(entries: &[Entry]) -> Vec<u8> {
    let mut p = Pickle::default();
    p.proto();
    p.empty_dict();
    p.mark();
    p.str("epoch");
    p.int(7);
    p.str("global_step");
    p.int(12345);
    p.str("pytorch-lightning_version");
    p.str("1.4.2");
    p.str("state_dict");
    write_state_dict(&mut p, entries);
    p.set_items();
    p.stop();
    p.0
}

/// A bare `torch.save(model.state_dict())` pickle.
fn plain_state_dict_pickle(entries: &[Entry]) -> Vec<u8> {
    let mut p = Pickle::default();
    p.proto();
    write_state_dict(&mut p, entries);
    p.stop();
    p.0
}

// ---------------------------------------------------------------------------------------------
// A stored (uncompressed) zip writer.
// ---------------------------------------------------------------------------------------------

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

fn zip_stored(files: &[(String, Vec<u8>)]) -> Vec<u8> {
    const DOS_DATE_1980_01_01: u16 = 0x21;
    let mut out = Vec::new();
    let mut central = Vec::new();
    for (name, data) in files {
        let offset = out.len() as u32;
        let crc = crc32(data);
        let size = data.len() as u32;
        // local file header
        out.extend(0x0403_4b50u32.to_le_bytes());
        out.extend(20u16.to_le_bytes()); // version needed
        out.extend(0u16.to_le_bytes()); // flags
        out.extend(0u16.to_le_bytes()); // method: stored
        out.extend(0u16.to_le_bytes()); // time
        out.extend(DOS_DATE_1980_01_01.to_le_bytes());
        out.extend(crc.to_le_bytes());
        out.extend(size.to_le_bytes()); // compressed
        out.extend(size.to_le_bytes()); // uncompressed
        out.extend((name.len() as u16).to_le_bytes());
        out.extend(0u16.to_le_bytes()); // extra length
        out.extend(name.as_bytes());
        out.extend(data);
        // central directory record
        central.extend(0x0201_4b50u32.to_le_bytes());
        central.extend(20u16.to_le_bytes()); // version made by
        central.extend(20u16.to_le_bytes()); // version needed
        central.extend(0u16.to_le_bytes()); // flags
        central.extend(0u16.to_le_bytes()); // method
        central.extend(0u16.to_le_bytes()); // time
        central.extend(DOS_DATE_1980_01_01.to_le_bytes());
        central.extend(crc.to_le_bytes());
        central.extend(size.to_le_bytes());
        central.extend(size.to_le_bytes());
        central.extend((name.len() as u16).to_le_bytes());
        central.extend(0u16.to_le_bytes()); // extra
        central.extend(0u16.to_le_bytes()); // comment
        central.extend(0u16.to_le_bytes()); // disk number
        central.extend(0u16.to_le_bytes()); // internal attributes
        central.extend(0u32.to_le_bytes()); // external attributes
        central.extend(offset.to_le_bytes());
        central.extend(name.as_bytes());
    }
    let cd_offset = out.len() as u32;
    let cd_size = central.len() as u32;
    out.extend(central);
    // end of central directory
    out.extend(0x0605_4b50u32.to_le_bytes());
    out.extend(0u16.to_le_bytes());
    out.extend(0u16.to_le_bytes());
    out.extend((files.len() as u16).to_le_bytes());
    out.extend((files.len() as u16).to_le_bytes());
    out.extend(cd_size.to_le_bytes());
    out.extend(cd_offset.to_le_bytes());
    out.extend(0u16.to_le_bytes());
    out
}

/// `torch.save`'s zip layout: `archive/data.pkl`, `archive/byteorder`, `archive/data/<key>`,
/// `archive/version`.
fn torch_zip(pickle: Vec<u8>, storages: &BTreeMap<String, Vec<u8>>) -> Vec<u8> {
    let mut files = vec![("archive/data.pkl".to_string(), pickle), ("archive/byteorder".into(), b"little".to_vec())];
    for (key, bytes) in storages {
        files.push((format!("archive/data/{key}"), bytes.clone()));
    }
    files.push(("archive/version".into(), b"3\n".to_vec()));
    zip_stored(&files)
}

// ---------------------------------------------------------------------------------------------
// The checkpoint of a tiny model.
// ---------------------------------------------------------------------------------------------

/// A checkpoint: pickle entries, storage bytes, and the float values every model parameter
/// must end up with.
struct Checkpoint {
    entries: Vec<Entry>,
    storages: BTreeMap<String, Vec<u8>>,
    expected: BTreeMap<String, NamedTensor>,
}

/// A tiny model's parameters with fresh random values: most as f32 in their own storage (as
/// torch.save writes them), the codebook as f16, the decoder's `norm_out` weight and bias sharing
/// one storage (second at an offset), plus `loss.` entries (discriminator weights and an int64
/// `num_batches_tracked`) and a non-`loss.` int64 buffer, which must all be skipped.
fn tiny_checkpoint(seed: u64) -> Checkpoint {
    let device = default_device();
    let model = VqModel::new(&ModelConfig::tiny(), 99, &device).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut c = Checkpoint { entries: Vec::new(), storages: BTreeMap::new(), expected: BTreeMap::new() };
    let mut shared: Vec<f32> = Vec::new();
    for (name, t) in named_tensors(&model) {
        let n = t.values.len();
        let mut values: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect();
        let key = c.entries.len().to_string();
        let (storage_type, storage_key, storage_numel, offset, bytes) = if name == "quantize.embedding.weight" {
            values = values.iter().map(|v| half::f16::from_f32(*v).to_f32()).collect();
            let bytes = values.iter().flat_map(|v| half::f16::from_f32(*v).to_le_bytes()).collect();
            ("HalfStorage", key, n, 0, Some(bytes))
        } else if name.starts_with("decoder.norm_out.") {
            let offset = shared.len();
            shared.extend(&values);
            ("FloatStorage", "shared".to_string(), 0, offset, None)
        } else {
            let bytes = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            ("FloatStorage", key, n, 0, Some(bytes))
        };
        if let Some(bytes) = bytes {
            c.storages.insert(storage_key.clone(), bytes);
        }
        c.expected.insert(name.clone(), NamedTensor { shape: t.shape.clone(), values });
        c.entries.push(Entry { name, storage_type, storage_key, storage_numel, offset, shape: t.shape });
    }
    let norm_out = ["decoder.norm_out.weight", "decoder.norm_out.bias"];
    assert_eq!(shared.len(), norm_out.iter().map(|n| c.expected[*n].values.len()).sum::<usize>());
    for e in c.entries.iter_mut().filter(|e| e.storage_key == "shared") {
        e.storage_numel = shared.len();
    }
    c.storages.insert("shared".into(), shared.iter().flat_map(|v| v.to_le_bytes()).collect());
    // entries the model does not have
    let extra: [(&str, &str, Vec<usize>); 4] = [
        ("loss.discriminator.main.0.weight", "FloatStorage", vec![4, 4, 4, 4]),
        ("loss.perceptual_loss.lin0.model.1.weight", "FloatStorage", vec![1, 64, 1, 1]),
        ("loss.discriminator.main.3.num_batches_tracked", "LongStorage", vec![]),
        ("encoder.num_batches_tracked", "LongStorage", vec![]),
    ];
    for (name, storage_type, shape) in extra {
        let n: usize = shape.iter().product();
        let key = format!("x{}", c.entries.len());
        let bytes: Vec<u8> = if storage_type == "LongStorage" {
            (0..n).flat_map(|i| (1000 + i as i64).to_le_bytes()).collect()
        } else {
            (0..n).flat_map(|i| (i as f32 * 0.5).to_le_bytes()).collect()
        };
        c.storages.insert(key.clone(), bytes);
        c.entries.push(Entry { name: name.into(), storage_type, storage_key: key, storage_numel: n, offset: 0, shape });
    }
    c
}

fn write(path: &Path, bytes: &[u8]) {
    std::fs::write(path, bytes).unwrap();
}

fn error_text(e: &ModelError) -> String {
    e.to_string()
}

#[test]
fn convert_tiny_lightning_checkpoint_keeps_every_parameter() {
    let tmp = tempfile::tempdir().unwrap();
    let ckpt = tmp.path().join("last.ckpt");
    let out = tmp.path().join("out.safetensors");
    let c = tiny_checkpoint(1);
    write(&ckpt, &torch_zip(lightning_pickle(&c.entries), &c.storages));

    // the reader sees every float tensor, no integer buffer
    let read = read_lightning_state_dict(&ckpt).unwrap();
    assert!(read.contains_key("loss.discriminator.main.0.weight"));
    assert!(!read.contains_key("encoder.num_batches_tracked"), "int64 buffers must be skipped");
    assert!(!read.contains_key("loss.discriminator.main.3.num_batches_tracked"));
    // norm_out.weight sits after norm_out.bias in their shared storage
    assert_eq!(read["decoder.norm_out.weight"], c.expected["decoder.norm_out.weight"], "storage offset");

    let cfg = ModelConfig::tiny();
    let used = convert_lightning_checkpoint(&ckpt, &out, Some(&cfg)).unwrap();
    assert_eq!(used, cfg);

    let (model, loaded_cfg) = load_model(&out, None, &default_device()).unwrap();
    assert_eq!(loaded_cfg, cfg, "config embedded in the output");
    let got = named_tensors(&model);
    assert_eq!(got.keys().collect::<Vec<_>>(), c.expected.keys().collect::<Vec<_>>());
    for (name, want) in &c.expected {
        let have = &got[name];
        assert_eq!(have.shape, want.shape, "{name}");
        assert_eq!(have.values, want.values, "{name}: values differ");
    }
    // the output holds no loss tensor
    let (tensors, _) = sgam_model::params::from_safetensors_bytes(&std::fs::read(&out).unwrap()).unwrap();
    assert!(tensors.keys().all(|k| !k.starts_with("loss.")));
    assert_eq!(tensors.len(), c.expected.len());
}

#[test]
fn convert_reads_a_plain_state_dict_without_the_lightning_wrapper() {
    let tmp = tempfile::tempdir().unwrap();
    let ckpt = tmp.path().join("model.pt");
    let out = tmp.path().join("out.safetensors");
    let c = tiny_checkpoint(2);
    write(&ckpt, &torch_zip(plain_state_dict_pickle(&c.entries), &c.storages));
    convert_lightning_checkpoint(&ckpt, &out, Some(&ModelConfig::tiny())).unwrap();
    let (model, _) = load_model(&out, None, &default_device()).unwrap();
    let got = named_tensors(&model);
    assert_eq!(got["encoder.conv_in.weight"], c.expected["encoder.conv_in.weight"]);
    assert_eq!(got["quantize.embedding.weight"], c.expected["quantize.embedding.weight"]);
}

#[test]
fn convert_rejects_a_checkpoint_that_does_not_fit_the_config() {
    let tmp = tempfile::tempdir().unwrap();
    let ckpt = tmp.path().join("last.ckpt");
    let out = tmp.path().join("out.safetensors");
    let mut c = tiny_checkpoint(3);
    c.entries.retain(|e| e.name != "post_quant_conv.bias");
    write(&ckpt, &torch_zip(lightning_pickle(&c.entries), &c.storages));
    let err = error_text(&convert_lightning_checkpoint(&ckpt, &out, Some(&ModelConfig::tiny())).unwrap_err());
    assert!(err.contains("last.ckpt") && err.contains("post_quant_conv.bias"), "{err}");
    assert!(!out.exists(), "no output on error");

    // a 64-entry codebook in the config, 32 in the file
    let c = tiny_checkpoint(4);
    write(&ckpt, &torch_zip(lightning_pickle(&c.entries), &c.storages));
    let cfg = ModelConfig { n_embed: 64, ..ModelConfig::tiny() };
    let err = error_text(&convert_lightning_checkpoint(&ckpt, &out, Some(&cfg)).unwrap_err());
    assert!(err.contains("last.ckpt") && err.contains("quantize.embedding.weight"), "{err}");
}

#[test]
fn convert_reports_corrupt_files_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out.safetensors");
    let cfg = ModelConfig::tiny();
    let c = tiny_checkpoint(5);
    let good = torch_zip(lightning_pickle(&c.entries), &c.storages);

    let truncated = tmp.path().join("truncated.ckpt");
    write(&truncated, &good[..good.len() / 2]);
    let not_zip = tmp.path().join("notes.ckpt");
    write(&not_zip, b"this is a text file, not a PyTorch checkpoint\n");
    let empty = tmp.path().join("empty.ckpt");
    write(&empty, b"");
    // a zip whose pickle stops half-way
    let cut_pickle = tmp.path().join("cut-pickle.ckpt");
    let pickle = lightning_pickle(&c.entries);
    write(&cut_pickle, &torch_zip(pickle[..pickle.len() / 2].to_vec(), &c.storages));
    // a zip whose storage bytes are shorter than the tensors need
    let short = tmp.path().join("short-storage.ckpt");
    let mut storages = c.storages.clone();
    storages.insert("0".into(), vec![0u8; 4]);
    write(&short, &torch_zip(lightning_pickle(&c.entries), &storages));
    let missing = tmp.path().join("missing.ckpt");

    for path in [&truncated, &not_zip, &empty, &cut_pickle, &short, &missing] {
        let name = path.file_name().unwrap().to_str().unwrap();
        let err = convert_lightning_checkpoint(path, &out, Some(&cfg));
        let err = error_text(&err.expect_err(name));
        assert!(err.contains(name), "error for {name} does not name the file: {err}");
        assert!(!out.exists());
    }
}
