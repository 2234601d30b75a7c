//! sgam-synth (to be written).
