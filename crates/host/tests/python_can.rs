//! Runs `python_can_smoke.py` (python-can's socketcand interface) against an in-process hub.
//!
//! Needs a Python with python-can: `$CANPOS_PYTHON`, else `target/venv-host/bin/python` in the
//! workspace. Skipped (with a message) when neither has python-can.

use std::path::PathBuf;
use std::process::Command;

use canpos_host::socketcand::Hub;

fn python() -> Option<PathBuf> {
    let manifest = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let candidates = std::env::var_os("CANPOS_PYTHON")
        .map(PathBuf::from)
        .into_iter()
        .chain([manifest.join("../../target/venv-host/bin/python")]);
    for p in candidates {
        let ok = Command::new(&p)
            .args(["-c", "import can"])
            .output()
            .is_ok_and(|o| o.status.success());
        if ok {
            return Some(p);
        }
    }
    None
}

#[test]
fn python_can_talks_through_the_hub() {
    let Some(py) = python() else {
        eprintln!("skipped: no Python with python-can (set CANPOS_PYTHON)");
        return;
    };
    let hub = Hub::bind("127.0.0.1:0").unwrap().spawn().unwrap();
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/python_can_smoke.py");
    let out = Command::new(py)
        .arg(script)
        .arg(hub.local_addr().port().to_string())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "python-can smoke test failed");
    assert!(stdout.contains("PASS"));
}
