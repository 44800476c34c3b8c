//! Decoders for `canpos monitor`: one line of text per frame. Pure functions of the frame and
//! what is known about the node, so they are unit-testable and never fail on odd input.

use canpos_stack::lss::{cs, Inquire, LssRequest, LssResponse, Part, MODE_CONFIGURATION};
use canpos_stack::nmt::{NmtCommand, NmtState, ALL_NODES};
use canpos_stack::sdo::wire::{Command, Mux, Request, Response, SEGMENT_DATA};
use canpos_stack::{cob, Frame};

use super::sdo::{abort_meaning, hex_string};

/// EMCY error codes of TH / E-Series (Table 5) and TMI, with the CiA 301 classes as fallback.
pub fn emcy_meaning(code: u16) -> &'static str {
    match code {
        0x0000 => "error reset / no error",
        0x3100 => "main (supply) voltage",
        0x5000 => "device hardware (transducer error)",
        0x6000 => "device software (TMI: event timer too small for the bit rate)",
        0x6300 => "data set (stored data lost or corrupt)",
        0x8100 => "communication",
        0x8110 => "CAN overrun (objects lost)",
        0x8120 => "CAN in error passive mode",
        0x8130 => "life guard error or heartbeat error",
        0x8140 => "recovered from bus-off",
        0x8150 => "CAN-ID collision",
        0x8210 => "PDO not processed due to length error",
        0x9080 => "cam state change (TMI)",
        0x9090 => "work area state change (TMI)",
        c => match c >> 12 {
            0x1 => "generic error",
            0x2 => "current",
            0x3 => "voltage",
            0x4 => "temperature",
            0x5 => "device hardware",
            0x6 => "device software",
            0x7 => "additional modules",
            0x8 => "monitoring / communication",
            0x9 => "external error",
            0xF => "additional functions",
            _ => "unknown",
        },
    }
}

/// Name of an NMT state as sent in heartbeats (bit 7, the guarding toggle, stripped).
pub fn nmt_state_name(b: u8) -> &'static str {
    match NmtState::from_code(b) {
        Some(NmtState::Initialising) => "boot-up",
        Some(NmtState::Stopped) => "stopped",
        Some(NmtState::Operational) => "operational",
        Some(NmtState::PreOperational) => "pre-operational",
        None => "unknown state",
    }
}

/// Name of an NMT command byte.
pub fn nmt_command_name(b: u8) -> &'static str {
    match NmtCommand::from_code(b) {
        Some(NmtCommand::Start) => "start",
        Some(NmtCommand::Stop) => "stop",
        Some(NmtCommand::EnterPreOperational) => "enter pre-operational",
        Some(NmtCommand::ResetNode) => "reset node",
        Some(NmtCommand::ResetCommunication) => "reset communication",
        None => "unknown command",
    }
}

/// Error register bits (0x1001) as names.
pub fn error_register(reg: u8) -> String {
    const NAMES: [&str; 8] = [
        "generic",
        "current",
        "voltage",
        "temperature",
        "communication",
        "profile",
        "reserved",
        "manufacturer",
    ];
    let set: Vec<&str> = (0..8)
        .filter(|b| reg & (1 << b) != 0)
        .map(|b| NAMES[b])
        .collect();
    if set.is_empty() {
        "none".into()
    } else {
        set.join("+")
    }
}

/// What the monitor knows about a node's process data (read by SDO when first seen).
#[derive(Clone, Debug, Default)]
pub struct NodeInfo {
    /// 0x6005/1: position step in nm.
    pub position_step_nm: Option<u32>,
    /// 0x6005/2: velocity step in 0.01 mm/s.
    pub velocity_step: Option<u32>,
    /// Valid TPDOs: (number 1…4, COB-ID, mapping entries `index<<16 | sub<<8 | bits`).
    pub tpdos: Vec<(u8, u16, Vec<u32>)>,
}

fn decimals(step_nm: u32) -> usize {
    if step_nm.is_multiple_of(1000) {
        3
    } else {
        6
    }
}

/// Decodes a TPDO's data with its mapping into `name=value` items.
pub fn decode_pdo(info: &NodeInfo, mapping: &[u32], data: &[u8]) -> String {
    let mut out = Vec::new();
    let mut bit = 0usize;
    for &m in mapping {
        let index = (m >> 16) as u16;
        let sub = (m >> 8) as u8;
        let bits = (m & 0xFF) as usize;
        if bits == 0 || bits > 32 {
            out.push(format!("{index:04X}:{sub:02X}=<{bits} bits?>"));
            break;
        }
        if bit + bits > data.len() * 8 {
            out.push(format!("{index:04X}:{sub:02X}=<PDO too short>"));
            break;
        }
        let mut raw: u64 = 0;
        for i in 0..bits {
            let b = bit + i;
            if data[b / 8] >> (b % 8) & 1 != 0 {
                raw |= 1 << i;
            }
        }
        bit += bits;
        let signed = {
            let shift = 64 - bits as u32;
            ((raw << shift) as i64) >> shift
        };
        out.push(match index {
            0x6020 => match info.position_step_nm {
                Some(s) => {
                    let mm = signed as f64 * s as f64 / 1e6;
                    format!("pos{sub}={mm:.prec$} mm", prec = decimals(s))
                }
                None => format!("pos{sub}={signed} steps"),
            },
            0x6030 => match info.velocity_step {
                Some(s) => format!("vel{sub}={:.2} mm/s", signed as f64 * s as f64 / 100.0),
                None => format!("vel{sub}={signed} steps"),
            },
            0x6300 => {
                let cams: Vec<String> = (0..bits.min(8))
                    .filter(|b| raw & (1 << b) != 0)
                    .map(|b| (b + 1).to_string())
                    .collect();
                if cams.is_empty() {
                    format!("cams{sub}=none")
                } else {
                    format!("cams{sub}=[{}]", cams.join(","))
                }
            }
            0x6400 => {
                let mut f = Vec::new();
                if raw & 4 != 0 {
                    f.push("below-low");
                }
                if raw & 2 != 0 {
                    f.push("above-high");
                }
                if raw & 1 != 0 {
                    f.push("out-of-range");
                }
                if f.is_empty() {
                    f.push("inside");
                }
                format!("area{sub}={}", f.join("+"))
            }
            0x6503 => format!(
                "alarms=0x{raw:04X}{}",
                if raw & 1 != 0 {
                    " (position error)"
                } else {
                    ""
                }
            ),
            0x6505 => format!("warnings=0x{raw:04X}"),
            _ => format!("{index:04X}:{sub:02X}={raw}"),
        });
    }
    if bit < data.len() * 8 && bit.div_ceil(8) < data.len() {
        out.push(format!("extra={}", hex_string(&data[bit.div_ceil(8)..])));
    }
    out.join(" ")
}

/// Describes a frame that is not a known TPDO. `None` when the COB-ID is not one a CANopen
/// device of the pre-defined connection set uses (the monitor then prints it raw).
pub fn describe(f: &Frame) -> Option<String> {
    if f.is_extended() {
        return None;
    }
    let id = f.id() as u16;
    let d = f.data();
    let node = (id & 0x7F) as u8;
    if f.is_remote() {
        return Some(match id & 0x780 {
            0x700 => format!("node {node} guarding request"),
            _ => format!("RTR 0x{id:03X}"),
        });
    }
    Some(match id {
        cob::NMT => match d {
            [c, ALL_NODES] => format!("NMT {} all nodes", nmt_command_name(*c)),
            [c, n] => format!("NMT {} node {n}", nmt_command_name(*c)),
            _ => format!("NMT malformed ({} bytes)", d.len()),
        },
        0x080 if d.len() <= 1 => "SYNC".to_string(),
        0x081..=0x0FF => match d {
            [lo, hi, reg, mfr @ ..] => {
                let code = u16::from_le_bytes([*lo, *hi]);
                format!(
                    "node {node} EMCY 0x{code:04X} {} reg 0x{reg:02X} ({}) data {}",
                    emcy_meaning(code),
                    error_register(*reg),
                    hex_string(mfr)
                )
            }
            _ => format!("node {node} EMCY malformed ({} bytes)", d.len()),
        },
        0x581..=0x5FF => format!("node {node} SDO ← {}", sdo_summary(d, false)),
        0x601..=0x67F => format!("node {node} SDO → {}", sdo_summary(d, true)),
        0x701..=0x77F => match d {
            [] => format!("node {node} guarding request"),
            [0] => format!("node {node} boot-up"),
            [s] if s & 0x80 != 0 => format!(
                "node {node} guarding answer {} (toggle 1)",
                nmt_state_name(*s)
            ),
            [s] => format!("node {node} heartbeat {}", nmt_state_name(*s)),
            _ => format!("node {node} error control malformed"),
        },
        cob::LSS_RX => format!("LSS → {}", lss_summary(d, true)),
        cob::LSS_TX => format!("LSS ← {}", lss_summary(d, false)),
        _ if node != 0 && (0x180..0x580).contains(&id) => {
            // Pre-defined connection set: TPDOn at 0x180 + 0x100·(n−1), RPDOn 0x80 above it.
            let fc = id & 0x780;
            let (kind, n) = if fc & 0x80 != 0 {
                ("TPDO", (fc - 0x080) >> 8)
            } else {
                ("RPDO", (fc - 0x100) >> 8)
            };
            format!("node {node} {kind}{n} {}", hex_string(d))
        }
        _ => return None,
    })
}

/// One-line summary of an SDO frame.
pub fn sdo_summary(d: &[u8], request: bool) -> String {
    let Ok(d) = <[u8; 8]>::try_from(d) else {
        return format!("malformed ({} bytes)", d.len());
    };
    let c = d[0];
    if Command(c).is_block() {
        return format!("block transfer 0x{c:02X}");
    }
    let mux = |m: Mux| format!("{:04X}:{:02X}", m.index, m.sub);
    let expedited = |size: Option<u32>, data: [u8; 4]| {
        // Without the size bit the size is unspecified; all 4 bytes are data.
        hex_string(&data[..size.unwrap_or(4) as usize])
    };
    let t = |toggle: bool| u8::from(toggle);
    let abort =
        |m: Mux, code: u32| format!("abort {} 0x{code:08X} {}", mux(m), abort_meaning(code));
    if request {
        match Request::parse(&d) {
            Request::Abort { mux: m, code } => abort(m, code),
            Request::DownloadInitiate {
                mux: m,
                expedited: true,
                size,
                data,
            } => format!("download {} = {}", mux(m), expedited(size, data)),
            Request::DownloadInitiate { mux: m, data, .. } => format!(
                "download {} segmented, {} bytes",
                mux(m),
                u32::from_le_bytes(data)
            ),
            Request::UploadInitiate { mux: m } => format!("upload {}", mux(m)),
            Request::UploadSegment { toggle } => {
                format!("upload segment (toggle {})", t(toggle))
            }
            Request::DownloadSegment { toggle, .. } => {
                format!("download segment (toggle {})", t(toggle))
            }
            _ => format!("command 0x{c:02X}"),
        }
    } else {
        match Response::parse(&d) {
            Response::Abort { mux: m, code } => abort(m, code),
            Response::DownloadInitiate { mux: m } => format!("download {} ok", mux(m)),
            Response::UploadInitiate {
                mux: m,
                expedited: true,
                size,
                data,
            } => format!("upload {} = {}", mux(m), expedited(size, data)),
            Response::UploadInitiate { mux: m, data, .. } => format!(
                "upload {} segmented, {} bytes",
                mux(m),
                u32::from_le_bytes(data)
            ),
            Response::UploadSegment {
                unused, last, data, ..
            } => format!(
                "upload segment {}{}",
                hex_string(&data[..SEGMENT_DATA - unused as usize]),
                if last { " (last)" } else { "" }
            ),
            Response::DownloadSegment { toggle } => {
                format!("download segment ok (toggle {})", t(toggle))
            }
            _ => format!("command 0x{c:02X}"),
        }
    }
}

/// The name of an LSS address part.
fn part_name(p: Part) -> &'static str {
    match p {
        Part::Vendor => "vendor",
        Part::Product => "product",
        Part::Revision => "revision",
        Part::Serial => "serial",
    }
}

/// One line for an LSS request.
fn lss_request_text(c: u8, r: LssRequest) -> String {
    match r {
        LssRequest::SwitchGlobal { mode } => format!(
            "switch global {}",
            if mode == MODE_CONFIGURATION {
                "configuration"
            } else {
                "waiting"
            }
        ),
        LssRequest::SwitchSelective { part, value } => {
            format!("switch selective {} 0x{value:08X}", part_name(part))
        }
        LssRequest::ConfigureNodeId { node_id } => format!("configure node-id {node_id}"),
        LssRequest::ConfigureBitTiming { table, index } => {
            format!("configure bit timing table {table} index {index}")
        }
        LssRequest::ActivateBitTiming { delay_ms } => {
            format!("activate bit timing, delay {delay_ms} ms")
        }
        LssRequest::StoreConfiguration => "store configuration".into(),
        LssRequest::Inquire(Inquire::Identity(p)) => format!("inquire {}", part_name(p)),
        LssRequest::Inquire(Inquire::NodeId) => "inquire node-id".into(),
        LssRequest::IdentifyNonConfigured => "identify non-configured slaves".into(),
        LssRequest::IdentifyRemote { value, .. } => {
            format!("identify remote slave 0x{c:02X} 0x{value:08X}")
        }
        LssRequest::Fastscan {
            id_number,
            bit_checked,
            sub,
            next,
        } => format!("fastscan id 0x{id_number:08X} bit {bit_checked} sub {sub} next {next}"),
    }
}

/// One line for an LSS answer.
fn lss_response_text(r: LssResponse) -> String {
    let status = |what: &str, c: u8, code: u8| {
        format!(
            "{what} status {code} ({})",
            super::lss::status_meaning(c, code)
        )
    };
    match r {
        LssResponse::SwitchSelective => "switch selective: selected".into(),
        LssResponse::ConfigureNodeId(s) => {
            status("configure node-id", cs::CONFIGURE_NODE_ID, s.code)
        }
        LssResponse::ConfigureBitTiming(s) => {
            status("configure bit timing", cs::CONFIGURE_BIT_TIMING, s.code)
        }
        LssResponse::StoreConfiguration(s) => status("store", cs::STORE_CONFIGURATION, s.code),
        LssResponse::Identity { part, value } => format!("{} 0x{value:08X}", part_name(part)),
        LssResponse::NodeId(id) => format!("node-id {id}"),
        LssResponse::IdentifyNonConfiguredSlave => "non-configured slave present".into(),
        LssResponse::IdentifySlave => "identify slave".into(),
    }
}

/// One-line summary of an LSS frame. A specifier of the other direction is read as that
/// direction's (a slave's answer seen on the master's COB-ID still says what it is); short
/// frames read as if padded with zeros.
pub fn lss_summary(d: &[u8], request: bool) -> String {
    let Some(&c) = d.first() else {
        return "empty".into();
    };
    let mut f = [0u8; 8];
    let n = d.len().min(8);
    f[..n].copy_from_slice(&d[..n]);
    let as_request = || LssRequest::parse(&f).map(|r| lss_request_text(c, r));
    let as_response = || LssResponse::parse(&f).map(lss_response_text);
    let text = if request {
        as_request().or_else(as_response)
    } else {
        as_response().or_else(as_request)
    };
    text.unwrap_or_else(|| format!("cs 0x{c:02X} {}", hex_string(d)))
}
