//! Procedural scene simulator (being filled in).
