//! H.264 MP4 videos of a run: `flythrough.mp4` (the generated frames in order) and the optional
//! `orbit.mp4` (the final mesh seen from a camera circling the world).
//!
//! Encoding is OpenH264 compiled from its bundled C source (the `openh264` crate's `source`
//! feature; nothing is downloaded), muxing is the `mp4` crate. Cisco's H.264 patent licence covers
//! only the OpenH264 binaries Cisco distributes, not a build from source: see the README before
//! shipping binaries; `sgam generate --no-mp4` turns MP4 output off.

use std::path::Path;

use anyhow::{bail, Context, Result};
use image::RgbImage;
use openh264::encoder::{BitRate, Encoder, EncoderConfig, FrameRate, FrameType, IntraFramePeriod, RateControlMode};
use openh264::formats::{RgbSliceU8, YUVBuffer};
use openh264::{OpenH264API, Timestamp};
use sgam_core::{Camera, Image, Intrinsics, Rigid3, TriMesh, Vec3};
use sgam_map::TsdfMap;

use sgam_pipeline::Keyframes;

/// Frame rate of `flythrough.mp4`, frames/s (one generated frame per video frame).
pub const FLYTHROUGH_FPS: u32 = 15;
/// Frames of `orbit.mp4` (one full turn) and its frame rate, frames/s.
pub const ORBIT_FRAMES: usize = 240;
pub const ORBIT_FPS: u32 = 30;
/// Size of `orbit.mp4`, pixels.
pub const ORBIT_SIZE: (u32, u32) = (640, 400);
/// Largest frame side OpenH264 encodes (level 5.2).
pub const MAX_SIDE: u32 = 3840;

/// What [`write_mp4`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VideoInfo {
    /// Frames (= MP4 samples) written.
    pub frames: usize,
    /// Picture size in the file (the frames' size rounded up to even numbers), pixels.
    pub width: u32,
    pub height: u32,
    /// File size, bytes.
    pub bytes: u64,
}

/// Bits per pixel per frame the rate control aims at (with a floor of 400 kbit/s): enough for
/// the generated frames' texture to stay sharp at a few MB per minute of 256 x 256 video.
const BITS_PER_PIXEL: f64 = 0.25;

/// Writes `frames` (8-bit sRGB, all one size, sides <= [`MAX_SIDE`]) as an H.264 MP4 at `fps`
/// frames/s, atomically: one video track, one sample per frame (none dropped), a key frame every
/// two seconds. Odd sides are padded to even ones by repeating the last row/column (4:2:0 needs
/// even sides). Errors name `path`; an error of the frame source stops the video with that error.
pub fn write_mp4<I>(path: &Path, frames: I, fps: u32) -> Result<VideoInfo>
where
    I: IntoIterator<Item = Result<RgbImage>>,
{
    if !(1..=240).contains(&fps) {
        bail!("{}: {fps} frames/s is outside 1..=240", path.display());
    }
    let mut encoder: Option<(Encoder, u32, u32)> = None;
    let mut samples: Vec<(Vec<u8>, bool)> = Vec::new();
    let (mut sps, mut pps) = (None::<Vec<u8>>, None::<Vec<u8>>);
    let mut size = (0u32, 0u32);
    for (i, frame) in frames.into_iter().enumerate() {
        let frame = frame.with_context(|| format!("{}: frame {i}", path.display()))?;
        let (w, h) = frame.dimensions();
        if i == 0 {
            if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
                bail!("{}: frames of {w} x {h} px (H.264 here: 1..={MAX_SIDE} px a side)", path.display());
            }
            size = (w, h);
        } else if (w, h) != size {
            bail!("{}: frame {i} is {w} x {h} px, frame 0 was {} x {} px", path.display(), size.0, size.1);
        }
        let frame = pad_to_even(frame);
        let (ew, eh) = frame.dimensions();
        let (enc, _, _) = match &mut encoder {
            Some(e) => e,
            None => {
                let bps = (BITS_PER_PIXEL * f64::from(ew * eh) * f64::from(fps)).max(400_000.0) as u32;
                let config = EncoderConfig::new()
                    .bitrate(BitRate::from_bps(bps))
                    .max_frame_rate(FrameRate::from_hz(fps as f32))
                    .rate_control_mode(RateControlMode::Off)
                    .skip_frames(false)
                    .intra_frame_period(IntraFramePeriod::from_num_frames(2 * fps))
                    .num_threads(1);
                let enc = Encoder::with_api_config(OpenH264API::from_source(), config)
                    .map_err(|e| anyhow::anyhow!("{}: cannot start the H.264 encoder: {e}", path.display()))?;
                encoder.insert((enc, ew, eh))
            }
        };
        let yuv = YUVBuffer::from_rgb8_source(RgbSliceU8::new(frame.as_raw(), (ew as usize, eh as usize)));
        let stream = enc
            .encode_at(&yuv, Timestamp::from_millis(i as u64 * 1000 / u64::from(fps)))
            .map_err(|e| anyhow::anyhow!("{}: H.264 encoding of frame {i} failed: {e}", path.display()))?;
        let key = matches!(stream.frame_type(), FrameType::IDR | FrameType::I);
        // Annex B (start codes) to MP4's length-prefixed NAL units; SPS/PPS go to the avcC box.
        let mut sample = Vec::new();
        for nal in sgam_io::split_annex_b(&stream.to_vec()) {
            match nal.first().map(|b| b & 0x1f) {
                Some(7) => sps = sps.or_else(|| Some(nal.to_vec())),
                Some(8) => pps = pps.or_else(|| Some(nal.to_vec())),
                Some(_) => {
                    sample.extend_from_slice(&(nal.len() as u32).to_be_bytes());
                    sample.extend_from_slice(nal);
                }
                None => {}
            }
        }
        if sample.is_empty() {
            bail!("{}: the H.264 encoder dropped frame {i}", path.display());
        }
        samples.push((sample, key));
    }
    let (Some(sps), Some(pps), Some((_, ew, eh))) = (sps, pps, encoder) else {
        bail!("{}: no frames to encode", path.display());
    };
    let bytes = sgam_io::write_h264_mp4(path, &samples, &sps, &pps, (ew, eh), fps)?;
    Ok(VideoInfo { frames: samples.len(), width: ew, height: eh, bytes })
}

/// `img` with odd sides padded by one repeated row / column.
fn pad_to_even(img: RgbImage) -> RgbImage {
    let (w, h) = img.dimensions();
    if w % 2 == 0 && h % 2 == 0 {
        return img;
    }
    let (ew, eh) = (w + w % 2, h + h % 2);
    RgbImage::from_fn(ew, eh, |x, y| *img.get_pixel(x.min(w - 1), y.min(h - 1)))
}

/// `RUN/flythrough.mp4`: every generated frame (`rgb/NNNNN.png`, `n` of them) in order at
/// [`FLYTHROUGH_FPS`]. Frames are read one at a time.
pub fn write_flythrough_mp4(dir: &Path, n: usize) -> Result<VideoInfo> {
    let frames = (0..n).map(|i| {
        let (rgb, _) = Keyframes::frame_paths(dir, i);
        Ok(image::open(&rgb).with_context(|| format!("{}: cannot read frame", rgb.display()))?.to_rgb8())
    });
    write_mp4(&dir.join("flythrough.mp4"), frames, FLYTHROUGH_FPS)
}

/// The cameras of the orbit video: `count` cameras on a circle around the centre of `mesh`'s
/// bounding box, at the overview camera's distance, looking at the centre from `pitch` above
/// the horizon (world up is `up`), `width x height` pixels; with the depth range to rasterize.
pub fn orbit_cameras(mesh: &TriMesh, up: Vec3, count: usize, width: u32, height: u32) -> Vec<(Camera, f32, f32)> {
    let Some(first) = mesh.positions.first() else { return Vec::new() };
    let (lo, hi) = mesh.positions.iter().fold((*first, *first), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
    let centre = (lo + hi) * 0.5;
    let radius = ((hi - lo).length() * 0.5).max(1e-3);
    let k = Intrinsics::from_fov_x(width, height, 1.0);
    // far enough that the bounding sphere fits the narrower field of view
    let half_fov = (0.5 * width.min(height) as f32 / k.fx).atan();
    let dist = radius / half_fov.sin() * 1.05;
    let up = up.normalize_or_zero();
    let side = if up.x.abs() < 0.9 { Vec3::X } else { Vec3::Y };
    let e1 = side.cross(up).normalize_or_zero();
    let e2 = up.cross(e1);
    let pitch = 0.6f32; // radians above the horizon
    (0..count)
        .filter_map(|i| {
            let a = std::f32::consts::TAU * i as f32 / count as f32;
            let dir = (e1 * a.cos() + e2 * a.sin()) * pitch.cos() + up * pitch.sin();
            let eye = centre + dir * dist;
            let pose = Rigid3::look_at(eye, centre, up)?;
            let near = (dist - radius).max(1e-3 * dist);
            Some((Camera::new(k, pose), near, dist + radius))
        })
        .collect()
}

/// `path` (e.g. `RUN/orbit.mp4`): one turn around the final mesh, rendered from the map.
pub fn write_orbit_mp4(path: &Path, map: &TsdfMap, mesh: &TriMesh, up: Vec3) -> Result<VideoInfo> {
    let cams = orbit_cameras(mesh, up, ORBIT_FRAMES, ORBIT_SIZE.0, ORBIT_SIZE.1);
    if cams.is_empty() {
        bail!("{}: the mesh is empty, nothing to orbit", path.display());
    }
    let frames =
        cams.iter().map(|(cam, near, far)| Ok(to_rgb8(&crate::overview::render_overview(map, cam, *near, *far))));
    write_mp4(path, frames, ORBIT_FPS)
}

/// `RUN/orbit.mp4` of a finished run: the map from `RUN/map.bin`, its mesh, world up `up`.
pub fn write_run_orbit_mp4(dir: &Path, up: Vec3) -> Result<VideoInfo> {
    let path = dir.join("map.bin");
    let bytes = std::fs::read(&path).with_context(|| format!("{}: cannot read the map", path.display()))?;
    let mut map = TsdfMap::read_from(&mut &bytes[..]).with_context(|| format!("{}: not a map", path.display()))?;
    drop(bytes);
    let mesh = map.extract_mesh();
    write_orbit_mp4(&dir.join("orbit.mp4"), &map, &mesh, up)
}

/// `[0, 1]` sRGB float image to 8 bits.
pub fn to_rgb8(img: &Image<[f32; 3]>) -> RgbImage {
    RgbImage::from_fn(img.width, img.height, |x, y| image::Rgb(img.at(x, y).map(sgam_io::to_srgb8)))
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use super::*;

    #[test]
    fn odd_frames_are_padded_by_repeating_the_edge() {
        let img = RgbImage::from_fn(3, 5, |x, y| image::Rgb([x as u8, y as u8, 7]));
        let p = pad_to_even(img);
        assert_eq!(p.dimensions(), (4, 6));
        assert_eq!(p.get_pixel(3, 5).0, [2, 4, 7]);
        assert_eq!(p.get_pixel(1, 2).0, [1, 2, 7]);
    }

    /// A moving colour pattern, frame `i` of a `w x h` clip.
    fn pattern(i: usize, w: u32, h: u32) -> RgbImage {
        RgbImage::from_fn(w, h, |x, y| {
            let t = i as u32 * 3;
            image::Rgb([
                ((x + t) * 255 / w) as u8,
                (y * 255 / h) as u8,
                if (x / 8 + y / 8) % 2 == 0 { 40 } else { 200 },
            ])
        })
    }

    /// The MP4 read back: (width, height, samples, duration s) and every frame decoded to RGB.
    fn read_back(path: &Path) -> ((u16, u16, u32, f64), Vec<RgbImage>) {
        let bytes = std::fs::read(path).unwrap();
        let size = bytes.len() as u64;
        let mut mp4 = mp4::Mp4Reader::read_header(Cursor::new(bytes), size).unwrap();
        assert_eq!(mp4.tracks().len(), 1);
        let track = mp4.tracks().values().next().unwrap();
        assert_eq!(track.media_type().unwrap(), mp4::MediaType::H264);
        let (id, w, h, n) = (track.track_id(), track.width(), track.height(), track.sample_count());
        let secs = track.duration().as_secs_f64();
        let mut annex_b = Vec::new();
        for ps in [track.sequence_parameter_set().unwrap(), track.picture_parameter_set().unwrap()] {
            annex_b.extend_from_slice(&[0, 0, 0, 1]);
            annex_b.extend_from_slice(ps);
        }
        let mut decoder = openh264::decoder::Decoder::new().unwrap();
        let mut frames = Vec::new();
        let mut rgb = vec![0u8; w as usize * h as usize * 3];
        for i in 1..=n {
            let sample = mp4.read_sample(id, i).unwrap().unwrap();
            let mut rest = &sample.bytes[..];
            while rest.len() >= 4 {
                let len = u32::from_be_bytes(rest[..4].try_into().unwrap()) as usize;
                annex_b.extend_from_slice(&[0, 0, 0, 1]);
                annex_b.extend_from_slice(&rest[4..4 + len]);
                rest = &rest[4 + len..];
            }
            if let Some(yuv) = decoder.decode(&annex_b).unwrap() {
                use openh264::formats::YUVSource;
                assert_eq!(yuv.dimensions(), (w as usize, h as usize));
                yuv.write_rgb8(&mut rgb);
                frames.push(RgbImage::from_raw(w as u32, h as u32, rgb.clone()).unwrap());
            }
            annex_b.clear();
        }
        for yuv in decoder.flush_remaining().unwrap() {
            yuv.write_rgb8(&mut rgb);
            frames.push(RgbImage::from_raw(w as u32, h as u32, rgb.clone()).unwrap());
        }
        ((w, h, n, secs), frames)
    }

    fn mean_abs_diff(a: &RgbImage, b: &RgbImage) -> f64 {
        let sum: u64 = a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| u64::from(x.abs_diff(*y))).sum();
        sum as f64 / a.as_raw().len() as f64
    }

    #[test]
    fn an_mp4_parses_back_with_every_frame_at_its_size() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("clip.mp4");
        let (w, h, n) = (96u32, 64u32, 45usize);
        let info = write_mp4(&path, (0..n).map(|i| Ok(pattern(i, w, h))), 15).unwrap();
        assert_eq!(info, VideoInfo { frames: n, width: w, height: h, bytes: std::fs::metadata(&path).unwrap().len() });
        let ((tw, th, samples, secs), frames) = read_back(&path);
        assert_eq!((u32::from(tw), u32::from(th), samples as usize), (w, h, n));
        assert!((secs - 3.0).abs() < 1e-3, "{secs} s for 45 frames at 15 frames/s");
        assert_eq!(frames.len(), n, "decoded frames");
        // decoded pictures are the frames (lossy: within a few levels on average), in order
        for i in [0, 22, 44] {
            let d = mean_abs_diff(&frames[i], &pattern(i, w, h));
            assert!(d < 8.0, "frame {i}: mean difference {d:.1} levels");
        }
        assert!(mean_abs_diff(&frames[44], &pattern(0, w, h)) > 2.0 * mean_abs_diff(&frames[44], &pattern(44, w, h)));
    }

    #[test]
    fn odd_frames_are_padded_and_bad_input_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("odd.mp4");
        let info = write_mp4(&path, (0..3).map(|i| Ok(pattern(i, 33, 17))), 10).unwrap();
        assert_eq!((info.width, info.height, info.frames), (34, 18, 3));
        assert_eq!(read_back(&path).0 .0, 34);
        let mixed = [Ok(pattern(0, 32, 32)), Ok(pattern(1, 32, 16))];
        let bad = dir.path().join("mixed.mp4");
        let e = write_mp4(&bad, mixed, 10).unwrap_err().to_string();
        assert!(e.contains("mixed.mp4") && e.contains("frame 1"), "{e}");
        assert!(!bad.exists());
        let e = write_mp4(&bad, std::iter::empty(), 10).unwrap_err().to_string();
        assert!(e.contains("no frames"), "{e}");
        let failing = [Ok(pattern(0, 32, 32)), Err(anyhow::anyhow!("rgb/00001.png: cannot read"))];
        let e = format!("{:#}", write_mp4(&bad, failing, 10).unwrap_err());
        assert!(e.contains("rgb/00001.png"), "{e}");
        assert!(write_mp4(&bad, [Ok(pattern(0, 8, 8))], 0).is_err());
    }

    #[test]
    fn the_flythrough_holds_every_frame_of_the_run() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("rgb")).unwrap();
        for i in 0..7 {
            pattern(i, 40, 30).save(dir.path().join(format!("rgb/{i:05}.png"))).unwrap();
        }
        let info = write_flythrough_mp4(dir.path(), 7).unwrap();
        assert_eq!((info.frames, info.width, info.height), (7, 40, 30));
        let ((_, _, samples, _), frames) = read_back(&dir.path().join("flythrough.mp4"));
        assert_eq!((samples, frames.len()), (7, 7));
        let e = write_flythrough_mp4(dir.path(), 8).unwrap_err();
        assert!(format!("{e:#}").contains("00007.png"), "{e:#}");
    }

    /// Encode time and size of 900 frames of 256 x 256 (the 900-step world's fly-through):
    /// `cargo test --release -p sgam video::tests::measure -- --ignored --nocapture`.
    #[test]
    #[ignore = "a measurement, not a test"]
    fn measure_900_frames_of_256() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.mp4");
        // frames like a fly-through: textured content sliding a few pixels per frame
        let base = RgbImage::from_fn(1200, 256, |x, y| {
            let h = (x.wrapping_mul(2654435761) ^ y.wrapping_mul(40503)) >> 7;
            image::Rgb([(x / 3 + (h & 31)) as u8, (y + (h >> 5 & 31)) as u8, ((x + y) / 5 + (h >> 10 & 31)) as u8])
        });
        let frames: Vec<RgbImage> =
            (0..900).map(|i| image::imageops::crop_imm(&base, i as u32 % 940, 0, 256, 256).to_image()).collect();
        let t = std::time::Instant::now();
        let info = write_mp4(&path, frames.into_iter().map(Ok), FLYTHROUGH_FPS).unwrap();
        let s = t.elapsed().as_secs_f64();
        eprintln!(
            "900 frames 256x256: {:.2} s ({:.1} ms/frame), {} bytes ({:.2} MB)",
            s,
            s * 1000.0 / 900.0,
            info.bytes,
            info.bytes as f64 / 1e6
        );
        assert_eq!(info.frames, 900);
    }

    #[test]
    fn orbit_cameras_look_at_the_mesh_centre_from_above() {
        let mesh = TriMesh {
            positions: vec![Vec3::new(-5.0, -3.0, -12.0), Vec3::new(7.0, 9.0, -11.0), Vec3::new(0.0, 0.0, -11.5)],
            colours: vec![],
            triangles: vec![[0, 1, 2]],
        };
        let cams = orbit_cameras(&mesh, Vec3::Z, 8, 64, 40);
        assert_eq!(cams.len(), 8);
        let centre = Vec3::new(1.0, 3.0, -11.5);
        for (cam, near, far) in &cams {
            let p = cam.world_from_camera.inverse().transform_point(centre);
            let uv = cam.intrinsics.project(p).unwrap();
            assert!((uv.x - 32.0).abs() < 1.0 && (uv.y - 20.0).abs() < 1.0, "centre projects to {uv:?}");
            assert!(cam.world_from_camera.translation.z > centre.z, "camera below the centre");
            // image up (-y) points to world up
            assert!((cam.world_from_camera.rotation * Vec3::NEG_Y).z > 0.0);
            for q in &mesh.positions {
                let z = cam.world_from_camera.inverse().transform_point(*q).z;
                assert!(z > *near && z < *far);
            }
        }
    }
}
