//! Multiply-add counts of the model's passes, from its config: what `sgam bench refine` divides
//! by the measured time to report GFLOP/s (a FLOP = one multiply or one add; a multiply-add
//! counts 2). Convolutions, dense layers and attention products only; norms, activations and
//! softmax are a few percent and left out.

use crate::config::ModelConfig;

/// Multiply-adds of one `k x k` convolution `c_in -> c_out` producing `h x w` outputs.
fn conv(c_in: usize, c_out: usize, k: usize, h: usize, w: usize) -> u64 {
    (c_in * c_out * k * k) as u64 * (h * w) as u64
}

fn resnet(c_in: usize, c_out: usize, h: usize, w: usize) -> u64 {
    conv(c_in, c_out, 3, h, w)
        + conv(c_out, c_out, 3, h, w)
        + if c_in != c_out { conv(c_in, c_out, 1, h, w) } else { 0 }
}

fn attention(c: usize, h: usize, w: usize) -> u64 {
    let n = (h * w) as u64;
    4 * conv(c, c, 1, h, w) + 2 * n * n * c as u64
}

/// Multiply-adds of the pieces of one refiner pass at `height x width` pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct PassMacs {
    /// Mask fusion, encoder and code head (or `quant_conv`).
    pub encoder: u64,
    /// `post_quant_conv` and decoder.
    pub decoder: u64,
}

/// Multiply-adds of the encoder (with mask fusion and code head) and decoder at `height x width`.
pub fn pass_macs(cfg: &ModelConfig, height: usize, width: usize) -> PassMacs {
    let p = cfg.patch_size.max(1);
    let (mut h, mut w) = (height / p, width / p);
    let mut enc = conv(cfg.input_channels(), 4, 1, height, width);
    enc += if p == 1 { conv(4, cfg.ch, 3, h, w) } else { conv(4, cfg.ch, p, h, w) };
    let mut res = cfg.resolution / p;
    let mut c = cfg.ch;
    for (i, m) in cfg.ch_mult.iter().enumerate() {
        let out = cfg.ch * m;
        for _ in 0..cfg.num_res_blocks {
            enc += resnet(c, out, h, w);
            c = out;
            if cfg.attn_resolutions.contains(&res) {
                enc += attention(c, h, w);
            }
        }
        if i + 1 < cfg.ch_mult.len() {
            (h, w, res) = (h / 2, w / 2, res / 2);
            enc += conv(c, c, 3, h, w);
        }
    }
    let mid = 2 * resnet(c, c, h, w) + if cfg.mid_attn { attention(c, h, w) } else { 0 };
    enc += mid + conv(c, cfg.z_channels, 3, h, w);
    enc += if cfg.code_head {
        conv(cfg.z_channels, cfg.n_embed, 1, h, w)
    } else {
        conv(cfg.z_channels, cfg.embed_dim, 1, h, w)
    };

    let mut dec = conv(cfg.embed_dim, cfg.z_channels, 1, h, w) + conv(cfg.z_channels, c, 3, h, w) + mid;
    for i in (0..cfg.ch_mult.len()).rev() {
        let out = cfg.ch * cfg.ch_mult[i];
        for _ in 0..=cfg.num_res_blocks {
            dec += resnet(c, out, h, w);
            c = out;
            if cfg.attn_resolutions.contains(&res) {
                dec += attention(c, h, w);
            }
        }
        if i != 0 {
            (h, w, res) = (h * 2, w * 2, res * 2);
            dec += conv(c, c, 3, h, w);
        }
    }
    dec += conv(c, 4 * p * p, 3, h, w);
    PassMacs { encoder: enc, decoder: dec }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_scale_with_the_pixels_and_match_a_hand_count() {
        let cfg = ModelConfig::compact();
        let a = pass_macs(&cfg, 128, 128);
        let b = pass_macs(&cfg, 256, 256);
        // no attention in the compact preset: every term is linear in the pixel count
        assert_eq!(b.encoder, 4 * a.encoder);
        assert_eq!(b.decoder, 4 * a.decoder);
        // a one-level model at 8x8 pixels with patch 2 (4x4 latent), by hand
        let tiny = ModelConfig {
            ch: 4,
            ch_mult: vec![1],
            num_res_blocks: 1,
            attn_resolutions: vec![],
            mid_attn: false,
            patch_size: 2,
            z_channels: 4,
            embed_dim: 4,
            n_embed: 8,
            norm_groups: 1,
            ..ModelConfig::tiny()
        };
        let n = 16u64; // latent cells
        let res = 2 * 4 * 4 * 9 * n; // a residual block: two 3x3 convs 4 -> 4
        let enc = 5 * 4 * 64 + 4 * 4 * 4 * n + res + 2 * res + 4 * 4 * 9 * n + 4 * 4 * n;
        let dec = 4 * 4 * n + 4 * 4 * 9 * n + 2 * res + 2 * res + 4 * 16 * 9 * n;
        assert_eq!(pass_macs(&tiny, 8, 8), PassMacs { encoder: enc, decoder: dec });
    }
}
