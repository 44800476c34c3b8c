//! canpos-host against a real SIL Kit (docs/SILKIT.md): a `sil-kit-registry` on 127.0.0.1 and
//! participants in this process. Needs `scripts/silkit.sh`; without it each test says so and
//! passes, unless `CANPOS_SILKIT_REQUIRED=1` (the test command sets it), where it fails.

use std::time::{Duration, Instant};

use canpos_host::silkit::{self, LocalRegistry, Participant, RegistryUri};

/// Generous: wall-clock waits on a loaded 2-core machine.
const START: Duration = Duration::from_secs(60);

fn api() -> Option<&'static silkit::Api> {
    match silkit::api() {
        Ok(a) => Some(a),
        Err(e) if std::env::var_os("CANPOS_SILKIT_REQUIRED").is_some_and(|v| v == "1") => {
            panic!("CANPOS_SILKIT_REQUIRED=1 but {e}")
        }
        Err(e) => {
            eprintln!("NOTE: SIL Kit test skipped: {e}");
            None
        }
    }
}

#[test]
fn the_library_is_sil_kit_5() {
    let Some(api) = api() else { return };
    assert_eq!(api.version().0, 5, "{:?}", api.version());
}

#[test]
fn a_participant_joins_and_a_taken_name_is_refused() {
    let Some(api) = api() else { return };
    let reg = LocalRegistry::start(START).expect("registry");
    let a = Participant::join(api, "canpos-test-a", reg.uri()).expect("join");
    assert_eq!(a.name(), "canpos-test-a");
    let e = Participant::join(api, "canpos-test-a", reg.uri())
        .err()
        .expect("a second participant of the same name is refused")
        .to_string();
    eprintln!("taken name: {e}");
    assert!(e.contains("canpos-test-a"), "{e}");
    // The first one is still there: its name stays taken; another name joins.
    let _b = Participant::join(api, "canpos-test-b", reg.uri()).expect("another name");
    drop(a);
}

#[test]
fn an_absent_registry_is_a_clear_error_not_a_hang() {
    let Some(api) = api() else { return };
    // A port nothing listens on: one the registry held and gave back.
    let reg = LocalRegistry::start(START).expect("registry");
    let uri: RegistryUri = reg.uri().clone();
    reg.stop();
    let t0 = Instant::now();
    let e = Participant::join(api, "canpos-test-alone", &uri)
        .err()
        .expect("no registry")
        .to_string();
    eprintln!("absent registry: {e}");
    assert!(e.contains(&uri.to_string()), "{e}");
    assert!(e.contains("SilKit_Participant_Create"), "{e}");
    // Bounded: SIL Kit gives up after its connect timeout (not a hang).
    assert!(
        t0.elapsed() < Duration::from_secs(120),
        "{:?}",
        t0.elapsed()
    );
}
