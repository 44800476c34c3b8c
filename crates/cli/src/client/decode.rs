//! Decoders for `canpos monitor`: one line of text per frame. Pure functions of the frame and
//! what is known about the node, so they are unit-testable and never fail on odd input.

use canpos_core::Frame;

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
    match b & 0x7F {
        0x00 => "boot-up",
        0x04 => "stopped",
        0x05 => "operational",
        0x7F => "pre-operational",
        _ => "unknown state",
    }
}

/// Name of an NMT command byte.
pub fn nmt_command_name(b: u8) -> &'static str {
    match b {
        0x01 => "start",
        0x02 => "stop",
        0x80 => "enter pre-operational",
        0x81 => "reset node",
        0x82 => "reset communication",
        _ => "unknown command",
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
        0x000 => match d {
            [c, 0] => format!("NMT {} all nodes", nmt_command_name(*c)),
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
        0x7E5 => format!("LSS → {}", lss_summary(d, true)),
        0x7E4 => format!("LSS ← {}", lss_summary(d, false)),
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
    let mux = format!("{:04X}:{:02X}", u16::from_le_bytes([d[1], d[2]]), d[3]);
    let val = u32::from_le_bytes([d[4], d[5], d[6], d[7]]);
    let exp_len = |c: u8| {
        if c & 1 != 0 {
            4 - ((c >> 2) & 3) as usize
        } else {
            4
        }
    };
    let c = d[0];
    match (c >> 5, request) {
        (4, _) => format!("abort {mux} 0x{val:08X} {}", abort_meaning(val)),
        (1, true) if c & 2 != 0 => {
            format!("download {mux} = {}", hex_string(&d[4..4 + exp_len(c)]))
        }
        (1, true) => format!("download {mux} segmented, {val} bytes"),
        (2, true) => format!("upload {mux}"),
        (3, true) => format!("upload segment (toggle {})", (c >> 4) & 1),
        (0, true) => format!("download segment (toggle {})", (c >> 4) & 1),
        (3, false) => format!("download {mux} ok"),
        (2, false) if c & 2 != 0 => {
            format!("upload {mux} = {}", hex_string(&d[4..4 + exp_len(c)]))
        }
        (2, false) => format!("upload {mux} segmented, {val} bytes"),
        (0, false) => format!(
            "upload segment {}{}",
            hex_string(&d[1..8 - ((c >> 1) & 7) as usize]),
            if c & 1 != 0 { " (last)" } else { "" }
        ),
        (1, false) => format!("download segment ok (toggle {})", (c >> 4) & 1),
        (5, _) | (6, _) => format!("block transfer 0x{c:02X}"),
        _ => format!("command 0x{c:02X}"),
    }
}

/// One-line summary of an LSS frame.
pub fn lss_summary(d: &[u8], request: bool) -> String {
    let Some(&cs) = d.first() else {
        return "empty".into();
    };
    let u = |i: usize| {
        let mut b = [0u8; 4];
        for (k, x) in b.iter_mut().enumerate() {
            *x = d.get(i + k).copied().unwrap_or(0);
        }
        u32::from_le_bytes(b)
    };
    let b = |i: usize| d.get(i).copied().unwrap_or(0);
    match (cs, request) {
        (0x04, _) => format!(
            "switch global {}",
            if b(1) == 1 {
                "configuration"
            } else {
                "waiting"
            }
        ),
        (0x40..=0x43, _) => format!(
            "switch selective {} 0x{:08X}",
            ["vendor", "product", "revision", "serial"][(cs - 0x40) as usize],
            u(1)
        ),
        (0x44, _) => "switch selective: selected".into(),
        (0x11, true) => format!("configure node-id {}", b(1)),
        (0x13, true) => format!("configure bit timing table {} index {}", b(1), b(2)),
        (0x11 | 0x13 | 0x17, false) => format!(
            "{} status {} ({})",
            match cs {
                0x11 => "configure node-id",
                0x13 => "configure bit timing",
                _ => "store",
            },
            b(1),
            super::lss::status_meaning(cs, b(1))
        ),
        (0x15, _) => format!(
            "activate bit timing, delay {} ms",
            u16::from_le_bytes([b(1), b(2)])
        ),
        (0x17, true) => "store configuration".into(),
        (0x5A..=0x5D, true) => format!(
            "inquire {}",
            ["vendor", "product", "revision", "serial"][(cs - 0x5A) as usize]
        ),
        (0x5A..=0x5D, false) => format!(
            "{} 0x{:08X}",
            ["vendor", "product", "revision", "serial"][(cs - 0x5A) as usize],
            u(1)
        ),
        (0x5E, true) => "inquire node-id".into(),
        (0x5E, false) => format!("node-id {}", b(1)),
        (0x4C, _) => "identify non-configured slaves".into(),
        (0x50, _) => "non-configured slave present".into(),
        (0x46..=0x4B, _) => format!("identify remote slave 0x{cs:02X} 0x{:08X}", u(1)),
        (0x4F, _) => "identify slave".into(),
        (0x51, _) => format!(
            "fastscan id 0x{:08X} bit {} sub {} next {}",
            u(1),
            b(5),
            b(6),
            b(7)
        ),
        _ => format!("cs 0x{cs:02X} {}", hex_string(d)),
    }
}
