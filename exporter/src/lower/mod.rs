//! Layer 1 of the exporter: the quantised model and its types, below the
//! quantiser that makes it and the encoder that writes it.

pub mod qmodel;
