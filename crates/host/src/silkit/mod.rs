//! Vector SIL Kit (issue 32, docs/SILKIT.md): `libSilKit.so`'s C API bound by hand and loaded at
//! run time, so canpos builds and tests without SIL Kit.

pub mod netsim;
