//! Engines: how fields are computed.
