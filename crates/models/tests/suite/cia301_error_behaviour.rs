//! CiA 301 §7.5.2.32 (0x1029 error behaviour, value 0 "change to pre-operational (only if
//! currently in operational)"): when the device's reaction to an error forces the node back to
//! pre-operational, that happens from Operational only; a stopped or pre-operational node stays
//! where it is, and PDOs stop with the change. Stated with an application whose reaction is
//! chosen by the test, and with the TMI's system-data error (its manual's reaction).

use canpos_encoder::{Fault, SystemDataError};
use canpos_models::{by_name, th::TH};
use canpos_stack::nmt::NmtState;
use canpos_stack::storage::RamStorage;
use canpos_stack::AppCtx;
use canpos_stack::{Application, Frame, Instant, Node};

/// An application whose cycle or fault reaction forces pre-operational when the sample / fault
/// says so.
struct Reacts;

impl Application for Reacts {
    type Sample = bool;
    type Fault = bool;
    type Config = canpos_models::DeviceConfig;
    type Profile = canpos_models::Switches;
    fn cycle(&mut self, force: &bool, _cx: &mut AppCtx<'_, Self>) -> bool {
        *force
    }
    fn inject(&mut self, force: bool, _active: bool, _cx: &mut AppCtx<'_, Self>) -> bool {
        force
    }
}

fn node_in(cmd: u8) -> Node<Reacts, RamStorage> {
    let mut n = Node::with_app(&TH, TH.default_config, Reacts, RamStorage::default());
    n.power_on(Instant::ZERO);
    while n.poll_transmit().is_some() {}
    if cmd != 0 {
        n.handle_frame(
            &Frame::new(0x000, &[cmd, 0]).unwrap(),
            Instant::from_millis(1),
        );
    }
    n
}

const STATES: [(u8, NmtState); 3] = [
    (0x01, NmtState::Operational),
    (0x02, NmtState::Stopped),
    (0x80, NmtState::PreOperational),
];

/// A process cycle whose reaction forces pre-operational.
#[test]
fn cia301_7_5_2_32_a_cycle_forces_pre_operational_only_from_operational() {
    for (cmd, state) in STATES {
        let mut n = node_in(cmd);
        assert_eq!(n.device().nmt_state(), state);
        n.update_sample(&false, Instant::from_millis(2));
        assert_eq!(n.device().nmt_state(), state, "no reaction, no change");
        n.update_sample(&true, Instant::from_millis(3));
        let after = match state {
            NmtState::Operational => NmtState::PreOperational,
            s => s,
        };
        assert_eq!(n.device().nmt_state(), after, "from {state:?}");
    }
}

/// A fault whose reaction forces pre-operational.
#[test]
fn cia301_7_5_2_32_a_fault_forces_pre_operational_only_from_operational() {
    for (cmd, state) in STATES {
        let mut n = node_in(cmd);
        n.inject_fault(false, true);
        assert_eq!(n.device().nmt_state(), state, "no reaction, no change");
        n.inject_fault(true, true);
        let after = match state {
            NmtState::Operational => NmtState::PreOperational,
            s => s,
        };
        assert_eq!(n.device().nmt_state(), after, "from {state:?}");
    }
}

/// TMI 002 §1.14: a system-data error sends the TMI to pre-operational; a stopped TMI stays
/// stopped (it only leaves Stopped by an NMT command), and its TPDOs stop with Operational.
#[test]
fn tmi_system_data_error_leaves_a_stopped_node_stopped() {
    let tmi = by_name("tmi").unwrap();
    let mut n = canpos_models::SensorNode::new(tmi, tmi.default_config, RamStorage::default());
    n.power_on(Instant::ZERO);
    while n.poll_transmit().is_some() {}
    n.handle_frame(
        &Frame::new(0x000, &[0x02, 0]).unwrap(),
        Instant::from_millis(1),
    );
    n.inject_fault(Fault::SystemData(SystemDataError::WrongScale), true);
    assert_eq!(n.device().nmt_state(), NmtState::Stopped);
    let mut n = canpos_models::SensorNode::new(tmi, tmi.default_config, RamStorage::default());
    n.power_on(Instant::ZERO);
    n.handle_frame(
        &Frame::new(0x000, &[0x01, 0]).unwrap(),
        Instant::from_millis(1),
    );
    assert!(n.device().tpdos().active());
    n.inject_fault(Fault::SystemData(SystemDataError::WrongScale), true);
    assert_eq!(n.device().nmt_state(), NmtState::PreOperational);
    assert!(!n.device().tpdos().active(), "PDOs stop with Operational");
}

/// TH: a supply-voltage error is reported (EMCY) and the node stays operational.
#[test]
fn th_an_error_without_that_reaction_keeps_the_node_operational() {
    let mut n = canpos_models::SensorNode::new(&TH, TH.default_config, RamStorage::default());
    n.power_on(Instant::ZERO);
    n.handle_frame(
        &Frame::new(0x000, &[0x01, 0]).unwrap(),
        Instant::from_millis(1),
    );
    n.inject_fault(Fault::SupplyVoltage, true);
    assert_eq!(n.device().nmt_state(), NmtState::Operational);
    assert!(n.device().tpdos().active());
}
