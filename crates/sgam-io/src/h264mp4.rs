//! MP4 (ISO-BMFF) files of one H.264 video track: the container around encoded frames (the
//! encoder, OpenH264, stays with the caller), written atomically.

use std::io::Cursor;
use std::path::Path;

use crate::IoError;

/// Writes `path`: the MP4 of length-prefixed H.264 `samples` (`(bytes, is_key_frame)`, one per
/// frame) with the stream's SPS / PPS, `size` pixels, `fps` frames per second. Returns the
/// file's size in bytes.
pub fn write_h264_mp4(
    path: &Path,
    samples: &[(Vec<u8>, bool)],
    sps: &[u8],
    pps: &[u8],
    size: (u32, u32),
    fps: u32,
) -> Result<u64, IoError> {
    let bytes = mux(samples, sps, pps, size.0, size.1, fps)
        .map_err(|e| IoError::Format { path: path.to_path_buf(), msg: format!("MP4 muxing failed: {e}") })?;
    crate::write_atomic(path, |w| std::io::Write::write_all(w, &bytes))?;
    Ok(bytes.len() as u64)
}

/// The MP4 file of length-prefixed H.264 `samples` (`(bytes, is_key_frame)`), one per frame.
pub(crate) fn mux(
    samples: &[(Vec<u8>, bool)],
    sps: &[u8],
    pps: &[u8],
    width: u32,
    height: u32,
    fps: u32,
) -> Result<Vec<u8>, Box<dyn std::error::Error>> {
    // A timescale of 1000 ticks per frame keeps every duration exact.
    let timescale = fps * 1000;
    let config = mp4::Mp4Config {
        major_brand: str::parse("isom")?,
        minor_version: 512,
        compatible_brands: ["isom", "iso2", "avc1", "mp41"].iter().map(|b| str::parse(b)).collect::<Result<_, _>>()?,
        timescale,
    };
    let mut writer = mp4::Mp4Writer::write_start(Cursor::new(Vec::new()), &config)?;
    writer.add_track(&mp4::TrackConfig {
        track_type: mp4::TrackType::Video,
        timescale,
        language: "und".into(),
        media_conf: mp4::MediaConfig::AvcConfig(mp4::AvcConfig {
            width: u16::try_from(width)?,
            height: u16::try_from(height)?,
            seq_param_set: sps.to_vec(),
            pic_param_set: pps.to_vec(),
        }),
    })?;
    for (i, (bytes, key)) in samples.iter().enumerate() {
        let sample = mp4::Mp4Sample {
            start_time: i as u64 * 1000,
            duration: 1000,
            rendering_offset: 0,
            is_sync: *key,
            bytes: mp4::Bytes::copy_from_slice(bytes),
        };
        writer.write_sample(1, &sample)?;
    }
    writer.write_end()?;
    Ok(writer.into_writer().into_inner())
}

/// The NAL units of an Annex B byte stream (start codes `00 00 01` / `00 00 00 01` removed).
pub fn split_annex_b(stream: &[u8]) -> Vec<&[u8]> {
    let mut starts = Vec::new();
    let mut i = 0;
    while i + 3 <= stream.len() {
        if stream[i] == 0 && stream[i + 1] == 0 && stream[i + 2] == 1 {
            starts.push(i + 3);
            i += 3;
        } else {
            i += 1;
        }
    }
    let mut nals = Vec::with_capacity(starts.len());
    for (k, &s) in starts.iter().enumerate() {
        let mut end = starts.get(k + 1).map_or(stream.len(), |&n| n - 3);
        // a 4-byte start code leaves one zero before the next 3-byte code
        while end > s && stream[end - 1] == 0 && k + 1 < starts.len() {
            end -= 1;
        }
        nals.push(&stream[s..end]);
    }
    nals
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn annex_b_splits_on_three_and_four_byte_start_codes() {
        let s = [0, 0, 0, 1, 0x67, 1, 2, 0, 0, 1, 0x68, 3, 0, 0, 0, 1, 0x65, 0, 4];
        let nals = split_annex_b(&s);
        assert_eq!(nals, vec![&[0x67, 1, 2][..], &[0x68, 3][..], &[0x65, 0, 4][..]]);
    }

    #[test]
    fn a_size_beyond_the_format_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.mp4");
        let err = write_h264_mp4(&path, &[(vec![0, 0, 0, 1, 0x65], true)], &[0x67], &[0x68], (70_000, 16), 15)
            .unwrap_err()
            .to_string();
        assert!(err.contains("big.mp4") && err.contains("MP4 muxing failed"), "{err}");
        assert!(!path.exists());
    }
}
