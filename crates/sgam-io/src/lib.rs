//! sgam-io (to be written).
