//! `canpos eds`: write a model's EDS (CiA 306) file.

use std::path::PathBuf;
use std::time::SystemTime;

use anyhow::{Context, Result};
use clap::Args;

use crate::sensor::export_unit;

/// `canpos eds`: write a model's EDS (CiA 306) file, or that of the unit an order code names.
#[derive(Args, Debug, Clone)]
pub struct EdsArgs {
    /// Model name: th, e-series, tmi.
    #[arg(
        long,
        required_unless_present = "order_code",
        conflicts_with = "order_code"
    )]
    pub model: Option<String>,
    /// Order code of a unit (e.g. EP00600MD341C304241Z02): its model with the defaults of its
    /// stroke, resolution, channels and bit rate, and the code as `OrderCode`.
    #[arg(long, value_name = "CODE")]
    pub order_code: Option<String>,
    /// Output file (default: standard output).
    #[arg(long, short = 'o')]
    pub output: Option<PathBuf>,
}

/// The file name an export writes into `FileName`: the output's, else `default`.
fn export_file_name(output: Option<&PathBuf>, default: String) -> String {
    output
        .and_then(|p| p.file_name())
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or(default)
}

/// Writes `text` to `output`, or to standard output.
fn write_export(output: Option<&PathBuf>, text: &str) -> Result<()> {
    match output {
        Some(p) => std::fs::write(p, text).with_context(|| format!("writing {}", p.display())),
        None => {
            use std::io::Write as _;
            std::io::stdout().write_all(text.as_bytes())?;
            Ok(())
        }
    }
}

/// Exports a model's EDS file: creation and modification date and time are the export's (UTC).
pub fn eds(a: EdsArgs) -> Result<i32> {
    let (model, cfg, order_code) = export_unit(a.model.as_deref(), a.order_code.as_deref())?;
    let default_name = if order_code.is_empty() {
        format!("canpos-{}.eds", model.name)
    } else {
        format!("{order_code}.eds")
    };
    let file_name = export_file_name(a.output.as_ref(), default_name);
    let (date, time) = crate::capture::eds_date_time(SystemTime::now());
    let info = canpos_stack::eds::EdsInfo {
        file_name: &file_name,
        date: &date,
        time: &time,
        order_code: &order_code,
        ..Default::default()
    };
    let mut text = String::new();
    canpos_stack::eds::write_eds(&mut text, model, &cfg, &info)
        .map_err(|_| anyhow::anyhow!("formatting the EDS failed"))?;
    write_export(a.output.as_ref(), &text)?;
    Ok(0)
}
