//! sgam-model (to be written).
