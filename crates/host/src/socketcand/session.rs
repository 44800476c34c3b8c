//! One socketcand connection's command state, as the reference daemon (linux-can/socketcand)
//! keeps it: no bus before `open`, then BCM, raw or control mode. Sans-IO: elements and time in;
//! replies (bytes), frames to put on the bus and frames to give the client out. The hub
//! ([`super::hub`]) does the I/O. The behaviour, command by command, is in docs/SOCKETCAND.md.

use std::time::{Duration, Instant, SystemTime};

use canpos_stack::Frame;

use super::codec::{self, CanId, Element, ErrorFrame, Mode};

/// Cyclic send jobs (`add`) one connection may hold.
pub const MAX_JOBS: usize = 256;
/// Subscriptions and filters one connection may hold.
pub const MAX_SUBSCRIPTIONS: usize = 256;
/// Shortest `add` cycle accepted; shorter ones are refused (the hub's timers wake at about
/// millisecond resolution, and a faster job would only flood the bus).
pub const MIN_CYCLE: Duration = Duration::from_micros(100);
/// Shortest statistics interval (socketcand's statistics thread wakes every 10 ms).
pub const MIN_STATISTICS: Duration = Duration::from_millis(10);

/// What the hub must do after a command, besides sending the reply bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Effect {
    /// Join this channel (after `open`).
    Join(String),
    /// Put this frame on the bus.
    Send(Frame),
    /// The client's transmit queue on the bus goes out in this order from now on.
    TxOrder(crate::bus::TxOrder),
    /// `< clock on >` (true) / `< clock off >`: the client becomes (or stops being) a timed
    /// participant of the channel bus's clock; the hub answers (`< ok >`, or an error on a bus
    /// without a clock).
    Clock(bool),
    /// `< at … >`: the timed client's horizon; the hub checks it against its bus and answers
    /// only a refusal.
    At(SystemTime),
    /// Raw mode began (its `< ok >` is the last thing written): the hub marks the end of the
    /// client's read there.
    RawStarted,
    /// The client's controller signalled an error on the bus (an `< error … >` of a bus-error
    /// class: protocol violation, missing ACK, bus error): an error frame goes on the channel's
    /// bus, and every controller's counters change as ISO 11898-1 says.
    ErrorFlag(ErrorFrame),
    /// Close the connection (a channel name the hub refuses).
    Close,
}

#[derive(Clone, Debug)]
struct Job {
    frame: Frame,
    interval: Duration,
    next: Instant,
}

#[derive(Clone, Debug)]
struct Subscription {
    id: CanId,
    interval: Duration,
    /// `filter`: the DLC and data mask; a frame passes when its masked data or DLC changed.
    mask: Option<Frame>,
    last_sent: Option<Instant>,
    last_content: Option<(u8, [u8; 8])>,
}

/// The command state of one client.
#[derive(Debug, Default)]
pub struct Session {
    mode: Option<Mode>,
    rtr: bool,
    errors: bool,
    jobs: Vec<Job>,
    subscriptions: Vec<Subscription>,
    statistics: Option<(Duration, Instant)>,
    rx: (u64, u64),
    tx: (u64, u64),
}

impl Session {
    /// A connection that has just been greeted with `< hi >`.
    pub fn new() -> Session {
        Session::default()
    }

    /// The current mode (`None`: no channel opened yet).
    pub fn mode(&self) -> Option<Mode> {
        self.mode
    }

    /// Whether the client opted into remote frames (`< rtr on >`).
    pub fn rtr(&self) -> bool {
        self.rtr
    }

    /// Handles one element from the client: appends the reply (if any) to `out` and returns what
    /// the hub has to do. `valid_channel` decides which channel names `open` accepts.
    pub fn handle(
        &mut self,
        el: Element,
        now: Instant,
        out: &mut Vec<u8>,
        valid_channel: impl Fn(&str) -> bool,
    ) -> Vec<Effect> {
        let mut fx = Vec::new();
        let unknown = |out: &mut Vec<u8>| codec::write_error_text(out, "unknown command");
        match (el, self.mode) {
            // Answered in every state (socketcand answers it once a channel is open; answering
            // it before costs nothing and lets a client probe the server).
            (Element::Echo, _) => out.extend_from_slice(codec::ECHO),
            (Element::Open(ch), None) => {
                if !valid_channel(&ch) {
                    codec::write_error_text(out, "could not open bus");
                    fx.push(Effect::Close);
                } else {
                    self.mode = Some(Mode::Bcm);
                    out.extend_from_slice(codec::OK);
                    fx.push(Effect::Join(ch));
                }
            }
            (Element::Mode(Mode::Isotp), Some(_)) => {
                codec::write_error_text(out, "isotp mode is not supported")
            }
            (Element::Mode(m), Some(cur)) if m != cur => {
                if cur == Mode::Bcm {
                    // socketcand closes the BCM socket on leaving the mode: jobs and filters end.
                    self.jobs.clear();
                    self.subscriptions.clear();
                }
                if cur == Mode::Control {
                    self.statistics = None;
                }
                self.mode = Some(m);
                out.extend_from_slice(codec::OK);
                if m == Mode::Raw {
                    fx.push(Effect::RawStarted);
                }
            }
            (Element::RtrOption(on), Some(_)) => {
                self.rtr = on;
                out.extend_from_slice(codec::OK);
            }
            (Element::ErrorsOption(on), Some(_)) => {
                self.errors = on;
                out.extend_from_slice(codec::OK);
            }
            (Element::TxOrderOption(order), Some(_)) => {
                out.extend_from_slice(codec::OK);
                fx.push(Effect::TxOrder(order));
            }
            (Element::ClockOption(on), Some(_)) => fx.push(Effect::Clock(on)),
            (Element::At(t), Some(_)) => fx.push(Effect::At(t)),
            (Element::ErrorFrame(e), Some(Mode::Raw | Mode::Bcm)) if self.errors => {
                // Only what is seen on the wire is the bus's business; a report of the client's
                // own controller (error passive, bus-off, restarted) is no other node's state.
                if e.class & codec::err_class::ON_THE_WIRE != 0 {
                    fx.push(Effect::ErrorFlag(e));
                }
            }
            (Element::Send(f), Some(Mode::Raw | Mode::Bcm)) => {
                self.count_tx(&f);
                fx.push(Effect::Send(f));
            }
            (Element::Add { interval, frame }, Some(Mode::Bcm)) => {
                let cid = CanId::of(&frame);
                if interval < MIN_CYCLE {
                    codec::write_error_text(out, "cycle time below 100 us");
                } else if let Some(j) = self.jobs.iter_mut().find(|j| CanId::of(&j.frame) == cid) {
                    // Like TX_SETUP with SETTIMER | STARTTIMER: the job restarts with its new
                    // content and cycle, the first frame now.
                    *j = Job {
                        frame,
                        interval,
                        next: now,
                    };
                } else if self.jobs.len() >= MAX_JOBS {
                    codec::write_error_text(out, "too many send jobs");
                } else {
                    self.jobs.push(Job {
                        frame,
                        interval,
                        next: now,
                    });
                }
            }
            (Element::Update(frame), Some(Mode::Bcm)) => {
                let cid = CanId::of(&frame);
                match self.jobs.iter_mut().find(|j| CanId::of(&j.frame) == cid) {
                    // The timer runs on; the next cycle sends the new content.
                    Some(j) => j.frame = frame,
                    None => codec::write_error_text(out, "no send job for this id"),
                }
            }
            (Element::Delete(cid), Some(Mode::Bcm)) => {
                let before = self.jobs.len();
                self.jobs.retain(|j| CanId::of(&j.frame) != cid);
                if self.jobs.len() == before {
                    codec::write_error_text(out, "no send job for this id");
                }
            }
            (Element::Subscribe { interval, id }, Some(Mode::Bcm)) => {
                self.subscribe(id, interval, None, out)
            }
            (Element::Filter { interval, mask }, Some(Mode::Bcm)) => {
                self.subscribe(CanId::of(&mask), interval, Some(mask), out)
            }
            (Element::Unsubscribe(id), Some(Mode::Bcm)) => {
                let before = self.subscriptions.len();
                self.subscriptions.retain(|s| s.id != id);
                if self.subscriptions.len() == before {
                    codec::write_error_text(out, "no subscription for this id");
                }
            }
            (Element::Statistics(ms), Some(Mode::Control)) => {
                self.statistics = (ms > 0).then(|| {
                    let every = Duration::from_millis(ms.into()).max(MIN_STATISTICS);
                    (every, now + every)
                });
            }
            (Element::Other(text), Some(Mode::Bcm)) if text.starts_with("muxfilter") => {
                codec::write_error_text(out, "muxfilter is not supported")
            }
            (Element::Malformed(name), Some(_)) => {
                codec::write_error_text(out, &format!("syntax error in {name} command"))
            }
            (Element::TooLong, _) => codec::write_error_text(
                out,
                &format!("element longer than {} bytes", codec::MAX_ELEMENT),
            ),
            (_, _) => unknown(out),
        }
        fx
    }

    fn subscribe(&mut self, id: CanId, interval: Duration, mask: Option<Frame>, out: &mut Vec<u8>) {
        let sub = Subscription {
            id,
            interval,
            mask,
            last_sent: None,
            last_content: None,
        };
        if let Some(s) = self.subscriptions.iter_mut().find(|s| s.id == id) {
            *s = sub;
        } else if self.subscriptions.len() >= MAX_SUBSCRIPTIONS {
            codec::write_error_text(out, "too many subscriptions");
        } else {
            self.subscriptions.push(sub);
        }
    }

    fn count_tx(&mut self, f: &Frame) {
        self.tx.0 += f.data().len() as u64;
        self.tx.1 += 1;
    }

    /// The earliest time [`Session::poll`] has something to do.
    pub fn next_deadline(&self) -> Option<Instant> {
        let jobs = self.jobs.iter().map(|j| j.next).min();
        let stat = self.statistics.map(|(_, t)| t);
        match (jobs, stat) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Runs what is due at `now`: the frames of due send jobs go into `send` (each job once per
    /// call; a job that fell behind skips the cycles it missed rather than bursting), a due
    /// statistics line into `out`.
    pub fn poll(&mut self, now: Instant, out: &mut Vec<u8>, send: &mut Vec<Frame>) {
        for j in &mut self.jobs {
            if j.next <= now {
                send.push(j.frame);
                j.next += j.interval;
                if j.next <= now {
                    // Behind by a whole cycle or more (the machine stalled): keep the phase.
                    let behind = now.duration_since(j.next).as_nanos() / j.interval.as_nanos();
                    j.next += j.interval * (behind as u32 + 1);
                }
            }
        }
        for f in send.iter() {
            self.tx.0 += f.data().len() as u64;
            self.tx.1 += 1;
        }
        if let Some((every, t)) = &mut self.statistics {
            if *t <= now {
                codec::write_stat(out, self.rx.0, self.rx.1, self.tx.0, self.tx.1);
                *t = (*t + *every).max(now);
            }
        }
    }

    /// Whether frames go to this client in the plain raw form ([`codec::write_frame`]), the same
    /// text for every such client: the hub formats a frame once for all of them.
    pub fn takes_plain_raw(&self) -> bool {
        self.mode == Some(Mode::Raw) && !self.rtr
    }

    /// Counts a frame given to the client in an already formatted form (see
    /// [`Session::takes_plain_raw`]).
    pub fn count_rx(&mut self, frame: &Frame) {
        self.rx.0 += frame.data().len() as u64;
        self.rx.1 += 1;
    }

    /// Writes a frame from the bus for the client as its mode wants it; `false` when the frame
    /// could not be written in raw mode (a remote frame with DLC > 0 for a client without the
    /// RTR extension).
    pub fn deliver(
        &mut self,
        frame: &Frame,
        ts: SystemTime,
        now: Instant,
        out: &mut Vec<u8>,
    ) -> bool {
        self.rx.0 += frame.data().len() as u64;
        self.rx.1 += 1;
        match self.mode {
            Some(Mode::Raw) if self.rtr => {
                codec::write_frame_rtr(out, frame, ts);
                true
            }
            Some(Mode::Raw) => codec::write_frame(out, frame, ts),
            Some(Mode::Bcm) => {
                let cid = CanId::of(frame);
                let Some(s) = self.subscriptions.iter_mut().find(|s| s.id == cid) else {
                    return true;
                };
                if let Some(m) = &s.mask {
                    let mut masked = [0u8; 8];
                    for (o, (d, k)) in masked.iter_mut().zip(frame.raw().iter().zip(m.raw())) {
                        *o = d & k;
                    }
                    let content = (frame.dlc(), masked);
                    if s.last_content == Some(content) {
                        return true;
                    }
                    // Throttled frames are not taken as seen: their change is reported later.
                    if s.last_sent
                        .is_some_and(|t| now.duration_since(t) < s.interval)
                    {
                        return true;
                    }
                    s.last_content = Some(content);
                } else if s
                    .last_sent
                    .is_some_and(|t| now.duration_since(t) < s.interval)
                {
                    return true;
                }
                s.last_sent = Some(now);
                if self.rtr && frame.is_remote() {
                    codec::write_frame_rtr(out, frame, ts);
                    true
                } else {
                    codec::write_bcm_frame(out, frame, ts)
                }
            }
            _ => true,
        }
    }

    /// Whether [`error_frame`](Self::error_frame) writes bus errors for this client.
    pub fn takes_errors(&self, all: bool) -> bool {
        (self.errors || all) && matches!(self.mode, Some(Mode::Raw | Mode::Bcm))
    }

    /// Writes a bus error for the client if it asked for them (`< errors on >`) or the hub
    /// serves them to everyone (`all`), in raw or BCM mode.
    pub fn error_frame(&self, e: &ErrorFrame, all: bool, out: &mut Vec<u8>) {
        if self.takes_errors(all) {
            codec::write_error_frame(out, e);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::socketcand::codec::Decoder;
    use std::time::UNIX_EPOCH;

    fn run(s: &mut Session, input: &[u8], now: Instant) -> (String, Vec<Effect>) {
        let mut out = Vec::new();
        let mut fx = Vec::new();
        for el in Decoder::new().feed_parse(input) {
            fx.extend(s.handle(el, now, &mut out, |c| c != "bad"));
        }
        (String::from_utf8(out).unwrap(), fx)
    }

    fn f(id: u16, d: &[u8]) -> Frame {
        Frame::new(id, d).unwrap()
    }

    #[test]
    fn handshake_and_unknown_commands_as_the_daemon_answers() {
        let t = Instant::now();
        let mut s = Session::new();
        assert_eq!(
            run(&mut s, b"< rawmode >< send 123 0 >< bogus >", t).0,
            "< error unknown command >< error unknown command >< error unknown command >"
        );
        let (o, fx) = run(&mut s, b"< open can0 >", t);
        assert_eq!(
            (o.as_str(), fx),
            ("< ok >", vec![Effect::Join("can0".into())])
        );
        assert_eq!(s.mode(), Some(Mode::Bcm));
        // Same mode again is no state change for socketcand: unknown command.
        assert_eq!(
            run(&mut s, b"< bcmmode >", t).0,
            "< error unknown command >"
        );
        assert_eq!(
            run(&mut s, b"< isotpmode >", t).0,
            "< error isotp mode is not supported >"
        );
        let (o, fx) = run(&mut s, b"< rawmode >", t);
        assert_eq!((o.as_str(), fx), ("< ok >", vec![Effect::RawStarted]));
        assert_eq!(
            run(&mut s, b"< open can1 >< add 0 1000 123 0 >", t).0,
            "< error unknown command >< error unknown command >"
        );
        assert_eq!(
            run(&mut s, b"< send 123 2 1 >", t).0,
            "< error syntax error in send command >"
        );
        let (o, fx) = run(&mut s, b"< send 123 1 aa >< echo >", t);
        assert_eq!(
            (o.as_str(), fx),
            ("< echo >", vec![Effect::Send(f(0x123, &[0xAA]))])
        );
    }

    /// `< txorder … >` (canpos extension): refused before a channel is open and when its
    /// argument is not `priority` / `fifo` (an error answer, no effect: the queue's order
    /// stays); once open, each valid one is answered and applied, repeated or not.
    #[test]
    fn txorder_refused_requests_change_nothing() {
        use crate::bus::TxOrder;
        let t = Instant::now();
        let mut s = Session::new();
        assert_eq!(
            run(&mut s, b"< txorder priority >", t),
            ("< error unknown command >".into(), vec![])
        );
        run(&mut s, b"< open can0 >", t);
        for bad in [
            &b"< txorder >"[..],
            b"< txorder lifo >",
            b"< txorder priority fifo >",
            b"< txorder PRIORITY >",
        ] {
            let (o, fx) = run(&mut s, bad, t);
            assert!(o.starts_with("< error "), "{o}");
            assert!(fx.is_empty(), "{fx:?}");
        }
        let (o, fx) = run(&mut s, b"< txorder priority >< txorder priority >", t);
        assert_eq!(o, "< ok >< ok >");
        assert_eq!(fx, vec![Effect::TxOrder(TxOrder::Priority); 2]);
        run(&mut s, b"< rawmode >", t);
        let (o, fx) = run(&mut s, b"< txorder fifo >", t);
        assert_eq!(
            (o.as_str(), fx),
            ("< ok >", vec![Effect::TxOrder(TxOrder::Fifo)])
        );
    }

    #[test]
    fn an_overlong_element_is_answered_in_every_state() {
        let t = Instant::now();
        let mut long = b"< send 123 1 ".to_vec();
        long.extend(std::iter::repeat_n(b'0', 1 << 20));
        long.extend_from_slice(b" >< echo >");
        let mut out = Vec::new();
        let mut s = Session::new();
        let mut d = Decoder::new();
        let mut rest = &long[..];
        while !rest.is_empty() {
            let (n, p) = d.next(rest);
            rest = &rest[n..];
            let el = match p {
                Some(codec::Piece::Body(b)) => Element::parse(b),
                Some(codec::Piece::TooLong) => Element::TooLong,
                None => continue,
            };
            assert!(s.handle(el, t, &mut out, |_| true).is_empty());
        }
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "< error element longer than 256 bytes >< echo >"
        );
    }

    #[test]
    fn a_refused_channel_is_an_error_and_a_close() {
        let mut s = Session::new();
        let (o, fx) = run(&mut s, b"< open bad >", Instant::now());
        assert_eq!(
            (o.as_str(), fx),
            ("< error could not open bus >", vec![Effect::Close])
        );
    }

    #[test]
    fn cyclic_jobs_on_a_virtual_clock() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut s = Session::new();
        run(&mut s, b"< open can0 >", t0);
        // A SYNC producer: COB-ID 0x080, 10 ms.
        assert_eq!(run(&mut s, b"< add 0 10000 080 0 >", t0).0, "");
        assert_eq!(s.next_deadline(), Some(t0));
        let mut sent = Vec::new();
        let mut out = Vec::new();
        for step in 0..=25 {
            let now = t0 + ms(step);
            if s.next_deadline().is_some_and(|d| d <= now) {
                let mut v = Vec::new();
                s.poll(now, &mut out, &mut v);
                sent.extend(v.into_iter().map(|f| (step, f)));
            }
        }
        let empty = f(0x80, &[]);
        assert_eq!(sent, vec![(0, empty), (10, empty), (20, empty)]);
        // update changes the content, keeps the timer.
        assert_eq!(run(&mut s, b"< update 080 1 5 >", t0 + ms(25)).0, "");
        assert_eq!(s.next_deadline(), Some(t0 + ms(30)));
        let mut v = Vec::new();
        s.poll(t0 + ms(30), &mut out, &mut v);
        assert_eq!(v, vec![f(0x80, &[5])]);
        // A stall of 35 ms: one frame, then back on the 10 ms phase.
        v.clear();
        s.poll(t0 + ms(75), &mut out, &mut v);
        assert_eq!(v.len(), 1);
        assert_eq!(s.next_deadline(), Some(t0 + ms(80)));
        assert_eq!(run(&mut s, b"< delete 080 >", t0).0, "");
        assert_eq!(s.next_deadline(), None);
        assert_eq!(
            run(&mut s, b"< delete 080 >< update 080 0 >< add 0 50 1 0 >", t0).0,
            "< error no send job for this id >< error no send job for this id >< error cycle time below 100 us >"
        );
        // Leaving BCM mode ends the jobs, as closing socketcand's BCM socket does.
        run(&mut s, b"< add 1 0 081 0 >< rawmode >", t0);
        assert_eq!(s.next_deadline(), None);
        assert!(out.is_empty());
    }

    #[test]
    fn job_count_is_bounded() {
        let t = Instant::now();
        let mut s = Session::new();
        run(&mut s, b"< open can0 >", t);
        for i in 0..MAX_JOBS {
            let cmd = format!("< add 1 0 {i:03X} 0 >");
            assert_eq!(run(&mut s, cmd.as_bytes(), t).0, "");
        }
        assert_eq!(
            run(&mut s, b"< add 1 0 7FF 0 >", t).0,
            "< error too many send jobs >"
        );
    }

    #[test]
    fn subscriptions_and_filters_throttle_and_match_content() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let ts = UNIX_EPOCH + Duration::from_secs(5);
        let mut s = Session::new();
        run(
            &mut s,
            b"< open can0 >< subscribe 0 10000 181 >< filter 0 0 182 2 FF 00 >",
            t0,
        );
        let mut out = Vec::new();
        for step in 0..20u64 {
            s.deliver(&f(0x181, &[step as u8]), ts, t0 + ms(step), &mut out);
        }
        s.deliver(&f(0x183, &[1]), ts, t0, &mut out);
        // Byte 0 under the mask: changes pass, the unmasked byte 1 does not matter.
        for (i, d) in [[1u8, 0], [1, 9], [2, 9], [2, 0]].iter().enumerate() {
            s.deliver(&f(0x182, d), ts, t0 + ms(i as u64), &mut out);
        }
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "< frame 181 5.000000 00  >< frame 181 5.000000 0A  >\
             < frame 182 5.000000 01 00  >< frame 182 5.000000 02 09  >"
        );
        assert_eq!(
            run(&mut s, b"< unsubscribe 181 >< unsubscribe 181 >", t0).0,
            "< error no subscription for this id >"
        );
    }

    #[test]
    fn remote_frames_only_for_clients_that_opted_in() {
        let t = Instant::now();
        let ts = UNIX_EPOCH + Duration::from_secs(1);
        let guard = Frame::remote(0x705, false, 0).unwrap();
        let guard1 = Frame::remote(0x705, false, 1).unwrap();
        let mut plain = Session::new();
        run(&mut plain, b"< open can0 >< rawmode >", t);
        let mut out = Vec::new();
        assert!(plain.deliver(&guard, ts, t, &mut out));
        assert!(!plain.deliver(&guard1, ts, t, &mut out));
        assert_eq!(String::from_utf8(out).unwrap(), "< frame 705 1.000000  >");

        let mut ext = Session::new();
        assert_eq!(
            run(&mut ext, b"< open can0 >< rawmode >< rtr on >", t).0,
            "< ok >< ok >< ok >"
        );
        let mut out = Vec::new();
        assert!(ext.deliver(&guard, ts, t, &mut out));
        assert!(ext.deliver(&guard1, ts, t, &mut out));
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "< rtr 705 1.000000 0 >< rtr 705 1.000000 1 >"
        );
        // Both forms of the extension's send give a remote frame, from any client.
        let (_, fx) = run(&mut plain, b"< send 705 1 R >< sendrtr 705 >", t);
        assert_eq!(fx, vec![Effect::Send(guard1), Effect::Send(guard)]);
    }

    #[test]
    fn error_frames_for_clients_that_asked_or_all() {
        let t = Instant::now();
        let e = ErrorFrame::for_state(
            crate::can::BusState::BusOff,
            UNIX_EPOCH + Duration::from_secs(2),
        );
        let mut s = Session::new();
        let mut out = Vec::new();
        s.error_frame(&e, true, &mut out);
        assert!(out.is_empty(), "nothing before open");
        run(&mut s, b"< open can0 >< rawmode >", t);
        s.error_frame(&e, false, &mut out);
        assert!(out.is_empty());
        s.error_frame(&e, true, &mut out);
        run(&mut s, b"< errors on >", t);
        s.error_frame(&e, false, &mut out);
        let one = "< error 040 2.000000 00 00 00 00 00 00 00 00 >";
        assert_eq!(String::from_utf8(out).unwrap(), format!("{one}{one}"));
        // A client that takes errors may signal one on the bus (a protocol error: an error
        // flag); its report of its own controller's state changes nothing; others may not.
        let (o, fx) = run(&mut s, one.as_bytes(), t);
        assert_eq!((o.as_str(), fx), ("", vec![]));
        let passive = "< error 004 2.000000 00 30 00 00 00 00 00 00 >";
        assert_eq!(run(&mut s, passive.as_bytes(), t), (String::new(), vec![]));
        let prot = "< error 008 2.000000 00 00 04 00 00 00 00 00 >";
        let (o, fx) = run(&mut s, prot.as_bytes(), t);
        assert_eq!(o, "");
        assert!(
            matches!(&fx[..], [Effect::ErrorFlag(e)] if e.class == 0x008),
            "{fx:?}"
        );
        let mut plain = Session::new();
        run(&mut plain, b"< open can0 >< rawmode >", t);
        assert_eq!(
            run(&mut plain, one.as_bytes(), t).0,
            "< error unknown command >"
        );
    }

    #[test]
    fn statistics_in_control_mode() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut s = Session::new();
        run(&mut s, b"< open can0 >", t0);
        let mut out = Vec::new();
        s.deliver(&f(0x181, &[1, 2]), UNIX_EPOCH, t0, &mut out);
        assert_eq!(
            run(&mut s, b"< statistics 100 >", t0).0,
            "< error unknown command >"
        );
        run(&mut s, b"< controlmode >< statistics 100 >", t0);
        assert_eq!(s.next_deadline(), Some(t0 + ms(100)));
        s.deliver(&f(0x181, &[3]), UNIX_EPOCH, t0, &mut out);
        assert!(out.is_empty(), "control mode gives no frames");
        let mut v = Vec::new();
        s.poll(t0 + ms(100), &mut out, &mut v);
        assert_eq!(String::from_utf8(out).unwrap(), "< stat 3 2 0 0 >");
        assert_eq!(
            run(&mut s, b"< statistics x >", t0).0,
            "< error syntax error in statistics command >"
        );
        run(&mut s, b"< statistics 0 >", t0);
        assert_eq!(s.next_deadline(), None);
    }
}
