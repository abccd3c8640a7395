//! Weather simulator (being filled in).
