//! canpos as FMI 3.0 co-simulation FMUs on the FMI-LS-BUS 1.0 CAN layer (docs/FMU.md).
//!
//! One shared library (`cdylib`) serves every FMU canpos writes; the FMU's
//! `resources/canpos-fmu.txt` says which [`kind::Kind`] an instance is. The same crate as an
//! `rlib` gives the packager (`canpos fmu`) the descriptions and the archive.

pub mod bus_fmu;
pub mod bussim;
pub mod ffi;
pub mod kind;
pub mod lsbus;
pub mod model;
pub mod package;
pub mod resource;
pub mod sensor;
