//! Finding the nodes on a bus: who answers an SDO read of the identity object.

use canpos_stack::cob;
use canpos_stack::sdo::wire::{Mux, Request, Response};
use std::collections::HashMap;
use std::io::{self};
use std::time::{Duration, Instant};

use canpos_host::transport::{RxFrame, Transport};
use canpos_stack::Frame;

use crate::client::{SdoClient, SdoError};
use crate::common::ms;

/// One node found by [`scan_bus`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ScanResult {
    /// Node-id.
    pub node: u8,
    /// 0x1000, when the node answered SDO.
    pub device_type: Option<u32>,
    /// 0x1018/1…4 (missing sub-indices are `None`).
    pub identity: [Option<u32>; 4],
    /// 0x1008.
    pub name: Option<String>,
    /// Last NMT state seen in a heartbeat / boot-up, if any; else operational when the node
    /// sent a PDO of the pre-defined connection set (see `state_inferred`).
    pub state: Option<u8>,
    /// `state` is inferred from PDOs, not heard in a heartbeat (issue 38 item 5).
    pub state_inferred: bool,
}

/// 0x1000/0, the device type: the object every CiA 301 node has.
pub const DEVICE_TYPE: Mux = Mux {
    index: 0x1000,
    sub: 0,
};

/// Finds nodes: SDO upload of 0x1000 to every node-id, plus heartbeats and boot-ups heard,
/// then reads each node's identity.
pub fn scan_bus(bus: &mut dyn Transport, timeout: Duration) -> io::Result<Vec<ScanResult>> {
    let mut found: HashMap<u8, ScanResult> = HashMap::new();
    // Nodes heard sending a TPDO of the pre-defined connection set.
    let mut pdo = [false; 128];
    let mut note = |found: &mut HashMap<u8, ScanResult>, rx: RxFrame| {
        let f = rx.frame;
        if f.is_extended() || f.is_remote() {
            return;
        }
        let id = f.id() as u16;
        let node = (id & 0x7F) as u8;
        match (id & 0x780, f.data()) {
            (cob::SDO_TX, d) if node != 0 => {
                let Ok(d) = <[u8; 8]>::try_from(d) else {
                    return;
                };
                match Response::parse(&d) {
                    Response::UploadInitiate {
                        mux: DEVICE_TYPE,
                        expedited: true,
                        size: Some(4),
                        data,
                    } => {
                        let e = found.entry(node).or_default();
                        e.node = node;
                        e.device_type = Some(u32::from_le_bytes(data));
                    }
                    Response::Abort {
                        mux: DEVICE_TYPE, ..
                    } => {
                        found.entry(node).or_default().node = node;
                    }
                    _ => {}
                }
            }
            (cob::ERRCTL, [s]) if node != 0 => {
                let e = found.entry(node).or_default();
                e.node = node;
                e.state = Some(*s & 0x7F);
                // PDOs before it tell nothing of the state it reports.
                pdo[usize::from(node)] = false;
            }
            (0x180 | 0x280 | 0x380 | 0x480, _) if node != 0 => pdo[usize::from(node)] = true,
            _ => {}
        }
    };
    // Requests go out in small bursts: a real adapter's transmit queue (and a slow hub client)
    // would drop frames if all 127 were queued at once.
    for node in 1..=127u8 {
        let mux = DEVICE_TYPE;
        bus.send(&Frame::std8(
            cob::SDO_RX + node as u16,
            Request::UploadInitiate { mux }.emit(),
        ))?;
        if node % 16 == 0 {
            let until = Instant::now() + ms(2);
            while let Some(rx) = bus.recv_deadline(until)? {
                note(&mut found, rx);
            }
        }
    }
    let until = Instant::now() + timeout;
    while let Some(rx) = bus.recv_deadline(until)? {
        note(&mut found, rx);
    }
    let mut nodes: Vec<ScanResult> = found.into_values().collect();
    nodes.sort_by_key(|n| n.node);
    // No heartbeat (or only a boot-up) but PDOs after it: only an operational node sends them
    // (CiA 301). Only for nodes found otherwise: a PDO's COB-ID alone may be another node's
    // (a remapped one).
    for n in &mut nodes {
        if matches!(n.state, None | Some(0)) && pdo[usize::from(n.node)] {
            n.state = Some(0x05);
            n.state_inferred = true;
        }
    }
    for n in &mut nodes {
        let mut c = SdoClient::new(bus, n.node, timeout);
        if n.device_type.is_none() {
            match c.read_u32(0x1000, 0) {
                Ok(v) => n.device_type = Some(v),
                // A node that does not answer SDO (stopped) yields no more information.
                Err(SdoError::Timeout) => continue,
                Err(SdoError::Io(e)) => return Err(e),
                Err(_) => {}
            }
        }
        for sub in 1..=4u8 {
            match c.read_u32(0x1018, sub) {
                Ok(v) => n.identity[sub as usize - 1] = Some(v),
                Err(SdoError::Io(e)) => return Err(e),
                Err(_) => {}
            }
        }
        match c.upload(0x1008, 0) {
            Ok(d) => {
                n.name = Some(
                    String::from_utf8_lossy(&d)
                        .trim_end_matches('\0')
                        .to_string(),
                )
            }
            Err(SdoError::Io(e)) => return Err(e),
            Err(_) => {}
        }
    }
    Ok(nodes)
}
