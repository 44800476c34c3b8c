//! The `canpos` command line as a library: the binary (`main.rs`) is a thin shell over these
//! modules, so that fuzz targets and tests reach the same parsers and checks the user does.
//!
//! One direction, from the bottom up: [`common`], [`limits`] and [`capture`] (shared parsers,
//! bus opening, exit codes, signals, file formats) ← [`client`] (SDO, LSS, decoding) ←
//! [`sensor`], [`scenario`], [`dashboard`], [`launch`] ← [`cmd`] (one file per subcommand).

pub mod capture;
pub mod client;
pub mod cmd;
pub mod common;
pub mod dashboard;
pub mod launch;
pub mod limits;
pub mod scenario;
pub mod sensor;
