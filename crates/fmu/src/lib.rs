//! canpos as FMI 3.0 co-simulation FMUs on the FMI-LS-BUS 1.0 CAN layer (docs/FMU.md).

pub mod bussim;
pub mod lsbus;
