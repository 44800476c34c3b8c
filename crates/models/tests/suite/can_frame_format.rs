//! The CAN frame the core sees (ISO 11898-1 classic data and remote frames, as CiA 301 uses
//! them): 11-bit (0…0x7FF) or 29-bit (0…0x1FFFFFFF) identifiers, 0…8 data bytes, remote
//! frames with a DLC and no data; the conversions to and from `embedded-can` drivers keep all of
//! it. And the virtual clock's arithmetic the core is driven by (µs, saturating).

use canpos_stack::{Duration, Frame, FrameError, Instant};
use embedded_can::{ExtendedId, Frame as _, Id, StandardId};

#[test]
fn standard_identifiers_have_11_bits_and_data_at_most_8_bytes() {
    let f = Frame::new(0x7FF, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap();
    assert_eq!(f.id(), 0x7FF);
    assert_eq!(f.std_id(), Some(0x7FF));
    assert_eq!(f.dlc(), 8);
    assert_eq!(f.data(), &[1, 2, 3, 4, 5, 6, 7, 8]);
    assert!(!f.is_extended() && !f.is_remote());
    assert_eq!(Frame::new(0x800, &[]), Err(FrameError::BadId));
    assert_eq!(Frame::new(0x123, &[0; 9]), Err(FrameError::TooLong));

    let f = Frame::new(0x123, &[0xAB, 0xCD]).unwrap();
    assert_eq!((f.id(), f.std_id(), f.dlc()), (0x123, Some(0x123), 2));
    assert_eq!(f.data(), &[0xAB, 0xCD]);
    assert_eq!(
        f.raw(),
        &[0xAB, 0xCD, 0, 0, 0, 0, 0, 0],
        "zero beyond the DLC"
    );
    let f = Frame::new(0, &[]).unwrap();
    assert_eq!((f.id(), f.dlc(), f.data()), (0, 0, &[][..]));

    for len in 0..=8 {
        let f = Frame::with_id(0x7FE, false, &[0x5A; 8][..len]).unwrap();
        assert_eq!((f.dlc() as usize, f.data().len()), (len, len));
    }
    assert_eq!(Frame::with_id(0x7FF, false, &[]).unwrap().id(), 0x7FF);
    assert_eq!(Frame::with_id(0x001, false, &[]).unwrap().id(), 0x001);
    assert_eq!(Frame::with_id(0x800, false, &[]), Err(FrameError::BadId));
    assert_eq!(
        Frame::with_id(0x100, false, &[0; 9]),
        Err(FrameError::TooLong)
    );
}

#[test]
fn extended_identifiers_have_29_bits_and_no_standard_id() {
    for id in [0x800, 0x1FFF_FFFE, 0x1FFF_FFFF, 0x123] {
        let f = Frame::with_id(id, true, &[7]).unwrap();
        assert_eq!((f.id(), f.std_id(), f.is_extended()), (id, None, true));
    }
    assert_eq!(
        Frame::with_id(0x2000_0000, true, &[]),
        Err(FrameError::BadId)
    );
}

#[test]
fn remote_frames_carry_a_dlc_and_no_data() {
    let f = Frame::remote(0x77F, false, 1).unwrap();
    assert!(f.is_remote() && !f.is_extended());
    assert_eq!((f.id(), f.dlc(), f.data()), (0x77F, 1, &[][..]));
    assert_eq!(Frame::remote(0x7FF, false, 8).unwrap().dlc(), 8);
    assert_eq!(Frame::remote(0x001, false, 0).unwrap().dlc(), 0);
    assert_eq!(Frame::remote(0x10, false, 9), Err(FrameError::TooLong));
    assert_eq!(Frame::remote(0x800, false, 0), Err(FrameError::BadId));
    assert_eq!(Frame::remote(0x7FE, false, 0).unwrap().id(), 0x7FE);
    let f = Frame::remote(0x1FFF_FFFF, true, 2).unwrap();
    assert_eq!((f.id(), f.is_extended(), f.dlc()), (0x1FFF_FFFF, true, 2));
    assert_eq!(
        Frame::remote(0x1FFF_FFFE, true, 0).unwrap().id(),
        0x1FFF_FFFE
    );
    assert_eq!(Frame::remote(0x800, true, 0).unwrap().id(), 0x800);
    assert_eq!(Frame::remote(0x2000_0000, true, 0), Err(FrameError::BadId));
}

/// The hot-path constructors keep the identifier to 11 bits and the DLC to 8.
#[test]
fn fixed_buffer_constructors_keep_11_bits_and_8_bytes() {
    let d = [1, 2, 3, 4, 5, 6, 7, 8];
    let f = Frame::std8(0x123, d);
    assert_eq!((f.id(), f.dlc(), f.data()), (0x123, 8, &d[..]));
    assert_eq!(Frame::std8(0x923, d).id(), 0x123);
    let f = Frame::std_len(0x185, d, 3);
    assert_eq!((f.id(), f.dlc(), f.data()), (0x185, 3, &d[..3]));
    assert_eq!(Frame::std_len(0x985, d, 3).id(), 0x185);
    assert_eq!(Frame::std_len(0x185, d, 8).dlc(), 8);
    assert_eq!(Frame::std_len(0x185, d, 9).dlc(), 8);
    assert_eq!(Frame::std_len(0x185, d, 200).dlc(), 8);
    assert_eq!(Frame::std_len(0x185, d, 0).data(), &[][..]);
}

/// Logs show frames as candump does: id, then the data bytes.
#[test]
fn frames_print_like_candump() {
    let s = |f: Frame| format!("{f:?}");
    assert_eq!(
        s(Frame::new(0x1FF, &[0x01, 0xA0, 0x0F]).unwrap()),
        "1FF [01 A0 0F]"
    );
    assert_eq!(s(Frame::new(0x05, &[]).unwrap()), "005 []");
    assert_eq!(s(Frame::new(0x05, &[0x42]).unwrap()), "005 [42]");
    assert_eq!(
        s(Frame::with_id(0x18FF_0001, true, &[0xFF, 0]).unwrap()),
        "18FF0001 [FF 00]"
    );
    assert_eq!(s(Frame::remote(0x77F, false, 1).unwrap()), "77F#R1");
    assert_eq!(
        FrameError::TooLong.to_string(),
        "CAN frame longer than 8 bytes"
    );
    assert_eq!(FrameError::BadId.to_string(), "CAN identifier out of range");
}

/// A HAL driver's `embedded-can` frames map onto the core's and back, identifier kind, RTR,
/// DLC and data intact.
#[test]
fn embedded_can_conversions_keep_every_field() {
    let std = StandardId::new(0x601).unwrap();
    let ext = ExtendedId::new(0x1ABC_DEF0).unwrap();

    let f = <Frame as embedded_can::Frame>::new(std, &[0x40, 0x00, 0x10, 0x00]).unwrap();
    assert_eq!(
        (f.id(), f.is_extended(), f.data()),
        (0x601, false, &[0x40, 0x00, 0x10, 0x00][..])
    );
    assert_eq!(embedded_can::Frame::id(&f), Id::Standard(std));
    assert_eq!(embedded_can::Frame::dlc(&f), 4);
    assert_eq!(embedded_can::Frame::data(&f), &[0x40, 0x00, 0x10, 0x00]);
    assert!(!embedded_can::Frame::is_extended(&f) && !f.is_remote_frame());
    assert!(<Frame as embedded_can::Frame>::new(std, &[0; 9]).is_none());

    let f = <Frame as embedded_can::Frame>::new(ext, &[1]).unwrap();
    assert_eq!((f.id(), f.is_extended()), (0x1ABC_DEF0, true));
    assert_eq!(embedded_can::Frame::id(&f), Id::Extended(ext));
    assert!(embedded_can::Frame::is_extended(&f));

    let r = <Frame as embedded_can::Frame>::new_remote(std, 8).unwrap();
    assert!(r.is_remote_frame() && r.is_remote());
    assert_eq!((r.id(), embedded_can::Frame::dlc(&r)), (0x601, 8));
    assert_eq!(embedded_can::Frame::data(&r), &[][..]);
    let r = <Frame as embedded_can::Frame>::new_remote(ext, 3).unwrap();
    assert_eq!((r.id(), r.is_extended(), r.dlc()), (0x1ABC_DEF0, true, 3));
    assert!(<Frame as embedded_can::Frame>::new_remote(std, 9).is_none());
    // A DLC is at most 8, never taken modulo 256.
    assert!(<Frame as embedded_can::Frame>::new_remote(std, 256).is_none());
    assert!(<Frame as embedded_can::Frame>::new_remote(ext, 264).is_none());
    assert_eq!(
        <Frame as embedded_can::Frame>::new_remote(std, 0).map(|r| r.dlc()),
        Some(0)
    );

    for f in [
        Frame::new(0x185, &[1, 2, 3]).unwrap(),
        Frame::new(0x000, &[]).unwrap(),
        Frame::with_id(0x1ABC_DEF0, true, &[9; 8]).unwrap(),
        Frame::remote(0x77F, false, 1).unwrap(),
        Frame::remote(0x0123_4567, true, 5).unwrap(),
    ] {
        let e: Frame = f.to_embedded().unwrap();
        assert_eq!(e, f);
        assert_eq!(Frame::from_embedded(&e), Some(f));
    }
}

/// The clock is in µs; sums saturate instead of wrapping (a `u64::MAX` deadline means never)
/// and differences of instants in the wrong order are zero.
#[test]
fn the_virtual_clock_counts_microseconds_and_saturates() {
    assert_eq!(Instant::from_micros(1234).micros(), 1234);
    assert_eq!(Instant::from_millis(3).micros(), 3000);
    assert_eq!(Instant::ZERO.micros(), 0);
    assert_eq!(Duration::from_micros(77).micros(), 77);
    assert_eq!(Duration::from_millis(5).micros(), 5000);
    assert_eq!(Duration::ZERO.micros(), 0);

    let t = Instant::from_millis(10);
    assert_eq!((t + Duration::from_micros(250)).micros(), 10_250);
    let mut u = t;
    u += Duration::from_millis(2);
    assert_eq!(u.micros(), 12_000);
    assert_eq!((u - t).micros(), 2000);
    assert_eq!((t - u).micros(), 0);
    assert_eq!(u.saturating_since(t).micros(), 2000);
    assert_eq!(t.saturating_since(u).micros(), 0);

    let end = Instant::from_micros(u64::MAX - 1);
    assert_eq!((end + Duration::from_micros(5)).micros(), u64::MAX);
    let mut e = end;
    e += Duration::from_micros(5);
    assert_eq!(e.micros(), u64::MAX);
}
