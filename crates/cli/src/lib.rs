//! The `canpos` command line as a library: the binary (`main.rs`) is a thin shell over these
//! modules, so that fuzz targets and tests reach the same parsers and checks the user does.

pub mod bench;
pub mod capture;
pub mod dashboard;
pub mod dcf;
pub mod device;
pub mod eds_run;
pub mod limits;
pub mod master;
pub mod scenario;
pub mod soak;
