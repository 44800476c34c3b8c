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

/// A fresh private directory for the state files of sensors that only live as long as this
/// command (the demo, `soak`, `bench`): a random name under the temporary directory, created
/// exclusively with mode 0700, so nobody can have planted a directory or a link there ahead;
/// removed when dropped.
pub(crate) fn private_state_dir(tag: &str) -> anyhow::Result<tempfile::TempDir> {
    use anyhow::Context;
    tempfile::Builder::new()
        .prefix(&format!("canpos-{tag}-"))
        .tempdir()
        .with_context(|| {
            format!(
                "cannot create a state directory in {}",
                std::env::temp_dir().display()
            )
        })
}
