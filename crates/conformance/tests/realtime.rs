//! The timing subset over socketcand in real time: heartbeat period (HB-02), event timer
//! (PDO-05) and the SYNC ratio (SYNC-03), each with the catalogue's ±10 % tolerance, against
//! a `canpos_host` runtime behind an in-process socketcand hub. Windows are short (1 s), and
//! the three models run on their own threads at once, so the test takes about 3 s.

use canpos_conformance::harness::nmt;
use canpos_conformance::{case, Harness, Outcome, SocketcandDut};
use canpos_models::Model;

fn run(model: &'static Model) {
    let dut = SocketcandDut::start(model).expect("hub and device start");
    let mut h = Harness::new(Box::new(dut));
    for id in ["HB-02", "PDO-05", "SYNC-03"] {
        // A defined start for each case, as the CTT's preparation step.
        h.reset(nmt::RESET_NODE);
        assert_eq!((case(id).run)(&mut h), Outcome::Pass, "{id} {}", model.name);
    }
}

#[test]
fn realtime_timing_all_models() {
    let threads: Vec<_> = canpos_models::all()
        .into_iter()
        .map(|m| std::thread::spawn(move || run(m)))
        .collect();
    for t in threads {
        if let Err(e) = t.join() {
            std::panic::resume_unwind(e);
        }
    }
}
