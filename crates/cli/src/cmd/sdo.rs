//! `canpos sdo`: read or write an object by SDO.

use anyhow::Result;
use clap::{Args, Subcommand};

use crate::client::{sdo, SdoClient, SdoError, ValueType};
use crate::common::{
    ms, open_bus, parse_index, parse_node, parse_sub, usage, BusArg, EXIT_OK, EXIT_REFUSED,
    EXIT_TIMEOUT,
};

/// `canpos sdo`: read or write an object.
#[derive(Args, Debug, Clone)]
pub struct SdoArgs {
    #[command(subcommand)]
    #[allow(missing_docs)]
    pub cmd: SdoCmd,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
    /// Time to wait for each answer, in ms.
    #[arg(long, global = true, default_value_t = sdo::DEFAULT_TIMEOUT_MS, value_name = "MS")]
    pub timeout: u64,
}

/// SDO operations. INDEX is hex (`0x1018` or `1018`); SUB is decimal or `0x`-hex.
#[derive(Subcommand, Debug, Clone)]
pub enum SdoCmd {
    /// Read (upload) an object and print its value.
    Read {
        /// Node-id 1…127.
        node: String,
        /// Object index, hex (0x1018 or 1018).
        index: String,
        /// Sub-index, decimal or 0x-hex (0 when left out: a variable's value, a record's or
        /// array's number of entries).
        #[arg(default_value = "0")]
        sub: String,
        /// How to show the value (default: number for ≤ 4 bytes, else text or hex).
        #[arg(long = "type", short = 't', value_enum)]
        ty: Option<ValueType>,
    },
    /// Write (download) an object.
    Write {
        /// Node-id 1…127.
        node: String,
        /// Object index, hex (0x1018 or 1018).
        index: String,
        /// Sub-index, decimal or 0x-hex.
        sub: String,
        /// The value: decimal or 0x-hex for numbers, text for str, hex bytes for bytes.
        #[arg(allow_hyphen_values = true)]
        value: String,
        /// The object's type (sets the size written).
        #[arg(long = "type", short = 't', value_enum)]
        ty: ValueType,
    },
}

fn sdo_failure(e: SdoError) -> Result<i32> {
    let code = match e {
        SdoError::Abort(_) | SdoError::Protocol(_) => EXIT_REFUSED,
        SdoError::Timeout => EXIT_TIMEOUT,
        SdoError::Io(e) => return Err(anyhow::Error::new(e).context("CAN transport failed")),
    };
    eprintln!("error: {e}");
    Ok(code)
}

/// Reads or writes one object.
pub fn sdo(a: SdoArgs) -> Result<i32> {
    match a.cmd {
        SdoCmd::Read {
            node,
            index,
            sub,
            ty,
        } => {
            let (node, index, sub) = (
                parse_node(&node, 1)?,
                parse_index(&index)?,
                parse_sub(&sub)?,
            );
            let mut bus = open_bus(&a.bus.bus)?;
            let mut c = SdoClient::new(&mut *bus, node, ms(a.timeout));
            match c.upload(index, sub) {
                Ok(d) => match ty {
                    None => {
                        println!("{}", sdo::format_auto(&d));
                        Ok(EXIT_OK)
                    }
                    Some(t) => match t.decode(&d) {
                        Ok(s) => {
                            println!("{s}");
                            Ok(EXIT_OK)
                        }
                        Err(m) => {
                            eprintln!("error: {m}; raw: {}", sdo::hex_string(&d));
                            Ok(EXIT_REFUSED)
                        }
                    },
                },
                Err(e) => sdo_failure(e),
            }
        }
        SdoCmd::Write {
            node,
            index,
            sub,
            value,
            ty,
        } => {
            let (node, index, sub) = (
                parse_node(&node, 1)?,
                parse_index(&index)?,
                parse_sub(&sub)?,
            );
            let data = ty.encode(&value).map_err(|m| usage!("{m}"))?;
            let mut bus = open_bus(&a.bus.bus)?;
            let mut c = SdoClient::new(&mut *bus, node, ms(a.timeout));
            match c.download(index, sub, &data) {
                Ok(()) => {
                    println!("ok");
                    Ok(EXIT_OK)
                }
                Err(e) => sdo_failure(e),
            }
        }
    }
}
