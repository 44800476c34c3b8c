//! The `Application` trait's defaults: "nothing to do". A CiA 301 device whose application
//! owns nothing (the `Plain` device served from an EDS, or an application that implements only
//! a part) behaves as the stack alone: NMT start is honoured, a process cycle or a fault never
//! forces pre-operational, nothing is stored unasked, and corrupt stored data raises the
//! generic EMCY 0x6300 (CiA 301 §7.2.7.1: 0x63xx data set).

use canpos_models::th::TH;
use canpos_models::tmi::TMI;
use canpos_models::Model;
use canpos_stack::nmt::NmtState;
use canpos_stack::storage::{self, RamStorage};
use canpos_stack::Application;
use canpos_stack::{Instant, Node, Plain};

/// An application that implements nothing but has a fault type (Plain's is uninhabited).
struct Quiet;

impl Application for Quiet {
    type Sample = ();
    type Fault = u8;
    type Config = canpos_models::DeviceConfig;
    type Profile = canpos_models::Switches;
}

fn started<
    A: Application<Config = canpos_models::DeviceConfig, Profile = canpos_models::Switches>,
>(
    app: A,
) -> Node<A, RamStorage> {
    started_on(&TH, TH.default_config, app)
}

/// The TH's table as a device with no application configuration (a `Plain` device).
fn plain_th() -> &'static canpos_stack::model::Model {
    Box::leak(Box::new(canpos_stack::model::Model {
        table: canpos_stack::Table { ..TH.table },
        profile: (),
        param: |c: &canpos_stack::CommConfig, p| {
            (TH.param)(
                &TH.default_config
                    .with_node_id(c.node_id)
                    .with_serial(c.serial),
                p,
            )
        },
        derive: |c| c,
        variant: None,
        default_config: canpos_stack::CommConfig {
            node_id: 127,
            bitrate_kbps: 125,
            serial: 1,
        },
    }))
}

fn started_on<A: Application>(
    model: &'static canpos_stack::ModelOf<A>,
    cfg: A::Config,
    app: A,
) -> Node<A, RamStorage> {
    let mut n = Node::with_app(model, cfg, app, RamStorage::default());
    n.power_on(Instant::ZERO);
    while n.poll_transmit().is_some() {}
    let start = canpos_stack::Frame::new(0x000, &[0x01, 0]).unwrap();
    n.handle_frame(&start, Instant::from_millis(10));
    n
}

#[test]
fn plain_device_starts_and_stays_operational_through_cycles() {
    let m = plain_th();
    let mut n = started_on(m, m.default_config, Plain);
    assert_eq!(n.device().nmt_state(), NmtState::Operational);
    for k in 1..=5 {
        n.update_sample(&(), Instant::from_millis(10 + k));
    }
    assert_eq!(n.device().nmt_state(), NmtState::Operational);
}

#[test]
fn default_cycle_and_fault_never_force_pre_operational() {
    let mut n = started(Quiet);
    n.update_sample(&(), Instant::from_millis(11));
    n.inject_fault(7, true);
    assert_eq!(n.device().nmt_state(), NmtState::Operational);
    n.inject_fault(7, false);
    assert_eq!(n.device().nmt_state(), NmtState::Operational);
}

#[test]
fn default_application_stores_nothing_by_itself() {
    let mut n = started(Quiet);
    for k in 1..=3 {
        n.update_sample(&(), Instant::from_millis(10 + k));
    }
    assert_eq!(n.storage_mut().saves, 0);
}

/// A "save" of all parameters stores the dictionary's values and no value of the
/// application's own: it has none (`Application::stored_value`).
#[test]
fn default_application_saves_no_value_of_its_own() {
    let mut n = Node::with_app(&TH, TH.default_config, Quiet, RamStorage::default());
    n.power_on(Instant::ZERO);
    let save = canpos_stack::Frame::new(
        0x600 + n.device().node_id() as u16,
        &[0x23, 0x10, 0x10, 1, b's', b'a', b'v', b'e'],
    )
    .unwrap();
    n.handle_frame(&save, Instant::from_millis(5));
    while n.poll_transmit().is_some() {}
    assert_eq!(n.storage_mut().saves, 1);
    let mut buf = [0u8; storage::IMAGE_MAX];
    let recs: Vec<_> = storage::load_image(n.storage_mut(), TH.features.tag, &mut buf)
        .unwrap()
        .collect();
    assert!(
        recs.iter().any(|&(k, _)| k == 0x0060_1001),
        "0x6010/1 stored: {recs:?}"
    );
    assert!(
        recs.iter().all(|&(k, _)| storage::app_record(k).is_none()),
        "{recs:?}"
    );
}

#[test]
fn corrupt_storage_raises_the_generic_data_set_emcy() {
    let mut n = Node::with_app(&TH, TH.default_config, Quiet, RamStorage::default());
    n.power_on(Instant::ZERO);
    // Store once ("save" 0x1010 sub 1), corrupt the medium, power-cycle.
    let save = canpos_stack::Frame::new(
        0x600 + n.device().node_id() as u16,
        &[0x23, 0x10, 0x10, 1, b's', b'a', b'v', b'e'],
    )
    .unwrap();
    n.handle_frame(&save, Instant::from_millis(5));
    while n.poll_transmit().is_some() {}
    assert_eq!(n.storage_mut().saves, 1);
    n.storage_mut().corrupt();
    n.power_off();
    n.power_on(Instant::from_millis(100));
    let emcy_id = 0x080 + n.device().node_id() as u16;
    let emcy: Vec<_> = core::iter::from_fn(|| n.poll_transmit())
        .filter(|f| f.std_id() == Some(emcy_id))
        .collect();
    assert!(
        emcy.iter().any(|f| f.data()[..2] == [0x00, 0x63]),
        "expected EMCY 0x6300, got {emcy:?}"
    );
}

/// An application that fixes its device's features at build time (`Application::FIXED`, as
/// a firmware for a device of its own does; the `plain` size reference is one).
struct Fixed;

impl Application for Fixed {
    type Sample = ();
    type Fault = u8;
    type Config = canpos_models::DeviceConfig;
    type Profile = canpos_models::Switches;
    const FIXED: Option<&'static Model> = Some(&TH);
}

#[test]
fn features_fixed_at_build_time_are_the_nodes() {
    let n = started(Fixed);
    assert!(core::ptr::eq(n.device().features(), &TH.features));
    assert_eq!(n.device().nmt_state(), NmtState::Operational);
}

/// Features of another model than the node's: a programming error.
struct Mismatched;

impl Application for Mismatched {
    type Sample = ();
    type Fault = u8;
    type Config = canpos_models::DeviceConfig;
    type Profile = canpos_models::Switches;
    const FIXED: Option<&'static Model> = Some(&TMI);
}

#[test]
#[cfg(debug_assertions)]
#[should_panic(expected = "FEATURES are the model's")]
fn features_of_another_model_fail_a_debug_build() {
    let _ = Node::with_app(&TH, TH.default_config, Mismatched, RamStorage::default());
}
