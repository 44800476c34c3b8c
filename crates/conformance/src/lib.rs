//! canpos-conformance: the CiA conformance-test-tool catalogue
//! (`docs/CONFORMANCE_CATALOGUE.md`) as an automated suite.
//!
//! * [`harness`]: the tool's master side (raw frames, NMT master, SYNC producer, guarding,
//!   capture, SDO client with expedited / segmented / block transfers and forged frames,
//!   sensor hooks in place of RPDO-triggered events).
//! * [`backend`]: a `canpos_stack::Node` on a virtual clock, or a real-time device over the
//!   socketcand transport.
//! * [`eds`]: a small INI / EDS reader for the EDS-driven cases.
//! * [`cases`]: one function per catalogue case.
//! * [`report`]: runs every case for every model and renders `docs/CONFORMANCE.md`.

pub mod backend;
pub mod cases;
pub mod eds;
pub mod harness;
pub mod report;

use canpos_models::Model;

pub use backend::{Backend, SocketcandDut, VirtualDut};
pub use cases::{Case, Outcome, CASES};
pub use harness::Harness;

/// A harness on a fresh virtual-clock device of `model`, past its boot-up.
pub fn virtual_harness(model: &'static Model) -> Harness {
    let mut h = Harness::new(Box::new(VirtualDut::new(model)));
    let boot = h.take();
    assert!(
        boot.iter()
            .any(|(_, f)| f.std_id() == Some(0x77F) && f.data() == [0]),
        "no boot-up at power-on"
    );
    h
}

/// The case with catalogue ID `id`.
pub fn case(id: &str) -> &'static Case {
    CASES
        .iter()
        .find(|c| c.id == id)
        .unwrap_or_else(|| panic!("no case {id}"))
}

/// Runs case `id` for `model` on the virtual clock (panics on failure).
pub fn run_virtual(id: &str, model: &'static Model) -> Outcome {
    let c = case(id);
    let mut h = virtual_harness(model);
    (c.run)(&mut h)
}

/// Runs case `id` on every model, and on the widest unit of a model whose units differ (the
/// two-channel TMI beside the one-channel default); an n.a. verdict is printed with its reason.
pub fn run_all_models(id: &str) {
    for m in canpos_models::all() {
        let widest = canpos_models::widest(m);
        let units: &[&'static Model] = if core::ptr::eq(widest, m) {
            &[m]
        } else {
            &[m, widest]
        };
        for &u in units {
            let channels = u.default_config.channels;
            match run_virtual(id, u) {
                Outcome::Pass => {}
                Outcome::Na(why) => println!("{id} {} ({channels} ch): n.a. ({why})", u.name),
            }
        }
    }
}
