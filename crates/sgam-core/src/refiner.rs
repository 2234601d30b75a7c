use crate::{Camera, RgbdFrame};

/// The incomplete RGB-D image handed to a [`Refiner`]: what the map shows at the target camera.
#[derive(Debug, Clone)]
pub struct Guidance {
    /// Target camera.
    pub camera: Camera,
    /// Rendered depth (valid where the map has geometry) and warped colour.
    pub frame: RgbdFrame,
    /// `true` where the pixel is missing (no geometry, or no source agreed on its colour).
    /// Row-major, same size as `frame`.
    pub missing: Vec<bool>,
    /// Seed for any random draw the refiner makes for this frame (derived from the run seed and
    /// the step index, so a resumed run draws exactly what an uninterrupted one would).
    pub seed: u64,
}

impl Guidance {
    /// Fraction of pixels marked missing.
    pub fn missing_fraction(&self) -> f32 {
        self.missing.iter().filter(|m| **m).count() as f32 / self.missing.len().max(1) as f32
    }
}

/// Completes an incomplete RGB-D guidance image into a full frame (the generative sensing
/// module). Implementations: the learned VQ model, and stand-ins for tests.
pub trait Refiner {
    /// Error type of this refiner.
    type Error: std::error::Error + Send + Sync + 'static;

    /// Returns a complete frame the same size as `guidance.frame`: colour in `[0, 1]`, valid
    /// planar depth in metres at every pixel the model can explain.
    fn refine(&mut self, guidance: &Guidance) -> Result<RgbdFrame, Self::Error>;

    /// Whether the frame the last [`Self::refine`] returned was invented where the guidance was
    /// missing, so that the generator's invented-pixel policy applies to it. `false` for a step
    /// answered with the truth (the oracle's steps of a closed-loop recording). Default: `true`.
    fn last_invented(&self) -> bool {
        true
    }
}
