//! One module per subcommand of `canpos` (what `main.rs` dispatches): each holds its clap
//! arguments and the function that runs it, over [`crate::common`], [`crate::client`] and the
//! libraries beside them.

pub mod bench;
pub mod bus;
pub mod ctl;
pub mod dashboard;
pub mod dcf;
pub mod demo;
pub mod eds;
pub mod fmu;
pub mod guard;
pub mod lss;
pub mod monitor;
pub mod netsim;
pub mod nmt;
pub mod record;
pub mod replay;
pub mod run;
pub mod scan;
pub mod scenario;
pub mod sdo;
pub mod soak;

#[cfg(test)]
mod tests;
