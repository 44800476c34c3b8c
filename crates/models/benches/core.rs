//! Criterion benchmarks of the device core, per model (issue 6): one operation = frame in →
//! the node's processing step (timers included) → frame out, as a host loop runs it.
//!
//! Instruction counts, which are free of machine noise, come from `canpos bench core` under
//! callgrind (`scripts/bench-instructions.sh`); these give wall-clock ns/op with statistics.
//! No object of any model is longer than 4 bytes, so a segmented *upload* never happens (the
//! server answers expedited); the segmented benches are a client-forced segmented download of
//! 4 bytes and a block upload of 0x1008 (models that support them; TMI supports neither).

use std::hint::black_box;

use canpos_encoder::Channels;
use canpos_encoder::Sample;
use canpos_models::SensorNode;
use canpos_models::{self as models, Model};
use canpos_stack::storage::NoStorage;
use canpos_stack::{Frame, Instant, Node};
use criterion::{criterion_group, criterion_main, Criterion};

/// A node of `model` with `channels` channels after power-on, in pre-operational.
fn booted(model: &'static Model, channels: u8) -> SensorNode<NoStorage> {
    let cfg = model.configure(model.default_config.with_channels(channels));
    let mut n = Node::new(model, cfg, NoStorage);
    n.power_on(Instant::from_micros(0));
    while n.poll_transmit().is_some() {}
    n
}

/// Timers if due, then one frame out (`Node::poll`, what the host runtime calls).
#[inline(always)]
fn step_out(n: &mut SensorNode<NoStorage>, now: Instant) -> Option<Frame> {
    n.poll(now)
}

fn sdo(n: &mut SensorNode<NoStorage>, id: u16, req: [u8; 8], now: Instant) -> [u8; 8] {
    n.handle_frame(&Frame::std8(0x600 + id, req), now);
    let r = step_out(n, now).expect("SDO answer");
    *r.raw()
}

fn expedited(index: u16, sub: u8, v: u32) -> [u8; 8] {
    let i = index.to_le_bytes();
    let b = v.to_le_bytes();
    [0x23, i[0], i[1], sub, b[0], b[1], b[2], b[3]]
}

fn bench_model(c: &mut Criterion, model: &'static Model) {
    let name = model.name;
    let mut g = c.benchmark_group(name);
    let mut n = booted(model, 1);
    let id = u16::from(n.device().node_id());
    let mut now = Instant::from_micros(1000);

    let up = Frame::std8(0x600 + id, [0x40, 0x00, 0x10, 0, 0, 0, 0, 0]);
    // Each operation is checked once before it is timed.
    assert_eq!(sdo(&mut n, id, *up.raw(), now)[0], 0x43, "{name}: upload");
    g.bench_function("sdo_expedited_upload_1000", |b| {
        b.iter(|| {
            now = Instant::from_micros(now.micros() + 1);
            n.handle_frame(black_box(&up), now);
            black_box(step_out(&mut n, now))
        })
    });

    let v = n.read_object(0x1014, 0).expect("0x1014");
    let down = Frame::std8(0x600 + id, expedited(0x1014, 0, v));
    assert_eq!(
        sdo(&mut n, id, *down.raw(), now)[0],
        0x60,
        "{name}: download"
    );
    g.bench_function("sdo_expedited_download_1014_4B", |b| {
        b.iter(|| {
            now = Instant::from_micros(now.micros() + 1);
            n.handle_frame(black_box(&down), now);
            black_box(step_out(&mut n, now))
        })
    });

    if model.features.sdo_segmented {
        // Initiate with size 4, then one segment with the 4 bytes (n = 3 unused, c = 1).
        let b4 = v.to_le_bytes();
        let init = [0x21, 0x14, 0x10, 0, 4, 0, 0, 0];
        let seg = [0x07, b4[0], b4[1], b4[2], b4[3], 0, 0, 0];
        assert_eq!(
            sdo(&mut n, id, init, now)[0],
            0x60,
            "{name}: segmented initiate"
        );
        assert_eq!(sdo(&mut n, id, seg, now)[0], 0x20, "{name}: segment");
        g.bench_function("sdo_segmented_download_1014_4B", |b| {
            b.iter(|| {
                now = Instant::from_micros(now.micros() + 1);
                let r1 = sdo(&mut n, id, init, now);
                let r2 = sdo(&mut n, id, seg, now);
                black_box((r1, r2))
            })
        });
    }
    if model.features.sdo_block {
        // Block upload of 0x1008 with CRC: initiate, start (one segment), ack (end), end.
        assert_eq!(
            sdo(&mut n, id, [0xA4, 0x08, 0x10, 0, 127, 0, 0, 0], now)[0] & 0xE0,
            0xC0
        );
        n.handle_frame(&Frame::std8(0x600 + id, [0xA3, 0, 0, 0, 0, 0, 0, 0]), now);
        assert_eq!(step_out(&mut n, now).expect("segment").raw()[0], 0x81);
        assert_eq!(
            sdo(&mut n, id, [0xA2, 1, 127, 0, 0, 0, 0, 0], now)[0] & 0xE3,
            0xC1
        );
        n.handle_frame(&Frame::std8(0x600 + id, [0xA1, 0, 0, 0, 0, 0, 0, 0]), now);
        assert!(n.poll_transmit().is_none(), "{name}: block upload end");
        g.bench_function("sdo_block_upload_1008", |b| {
            b.iter(|| {
                now = Instant::from_micros(now.micros() + 1);
                let r1 = sdo(&mut n, id, [0xA4, 0x08, 0x10, 0, 127, 0, 0, 0], now);
                n.handle_frame(&Frame::std8(0x600 + id, [0xA3, 0, 0, 0, 0, 0, 0, 0]), now);
                let seg = step_out(&mut n, now).expect("segment");
                let r3 = sdo(&mut n, id, [0xA2, 1, 127, 0, 0, 0, 0, 0], now);
                n.handle_frame(&Frame::std8(0x600 + id, [0xA1, 0, 0, 0, 0, 0, 0, 0]), now);
                black_box((r1, seg, r3))
            })
        });
    }

    // LSS inquire node-id in configuration state.
    let mut l = booted(model, 1);
    l.handle_frame(&Frame::std8(0x7E5, [0x04, 1, 0, 0, 0, 0, 0, 0]), now);
    let inq = Frame::std8(0x7E5, [0x5E, 0, 0, 0, 0, 0, 0, 0]);
    l.handle_frame(&inq, now);
    assert_eq!(
        step_out(&mut l, now).map(|f| f.raw()[1]),
        Some(id as u8),
        "{name}: LSS"
    );
    g.bench_function("lss_inquire_node_id", |b| {
        b.iter(|| {
            now = Instant::from_micros(now.micros() + 1);
            l.handle_frame(black_box(&inq), now);
            black_box(step_out(&mut l, now))
        })
    });

    // One TPDO1 with the default mapping at a 1 ms event timer.
    let mut t = booted(model, 1);
    let mut tnow = Instant::from_micros(1000);
    t.handle_frame(
        &Frame::std8(0x600 + id, [0x2B, 0x00, 0x18, 5, 1, 0, 0, 0]),
        tnow,
    );
    t.handle_frame(&Frame::std_len(0x000, [0x01, 0, 0, 0, 0, 0, 0, 0], 2), tnow);
    while t.poll_transmit().is_some() {}
    tnow = t.poll_timeout().expect("TPDO deadline");
    let first = step_out(&mut t, tnow).expect("TPDO");
    assert_eq!(first.std_id(), Some(0x180 + id), "{name}: TPDO1");
    tnow = Instant::from_micros(tnow.micros() + 1000);
    g.bench_function("tpdo_default_mapping", |b| {
        b.iter(|| {
            let f = step_out(&mut t, black_box(tnow));
            tnow = Instant::from_micros(tnow.micros() + 1000);
            black_box(f)
        })
    });

    // One measurement cycle, every channel, every cam enabled, work areas on (limits are the
    // measuring range by default), a magnet moving through the range.
    let ch = model.max_channels();
    let mut m = booted(model, ch);
    let mut mnow = Instant::from_micros(1000);
    for sub in 1..=ch {
        for enable in [0xFFu32, 0x0F, 0x03, 0x01] {
            let r = sdo(&mut m, id, expedited(0x6301, sub, enable).map_or_u8(), mnow);
            if r[0] == 0x60 {
                break;
            }
        }
    }
    while m.poll_transmit().is_some() {}
    let mut s = Sample::default();
    let mut pos = 0i64;
    g.bench_function("measurement_cycle_all_cams_work_areas", |b| {
        b.iter(|| {
            mnow = Instant::from_micros(mnow.micros() + 1000);
            pos = (pos + 1_000_000) % 200_000_000;
            for (k, p) in s.positions_nm.iter_mut().take(ch as usize).enumerate() {
                *p = Some(pos + k as i64 * 10_000_000);
            }
            m.update_sample(black_box(&s), mnow);
            while let Some(f) = m.poll_transmit() {
                black_box(f);
            }
        })
    });
    g.finish();
}

/// `expedited` writes 4 bytes; cam enable is one byte (0x2F, size indicated 1).
trait U8Write {
    fn map_or_u8(self) -> [u8; 8];
}
impl U8Write for [u8; 8] {
    fn map_or_u8(mut self) -> [u8; 8] {
        self[0] = 0x2F;
        self
    }
}

fn benches(c: &mut Criterion) {
    for m in models::all() {
        bench_model(c, m);
    }
}

criterion_group!(core, benches);
criterion_main!(core);
