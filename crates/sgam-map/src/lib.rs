//! sgam-map (to be written).
