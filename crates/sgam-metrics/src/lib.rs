//! sgam-metrics (to be written).
