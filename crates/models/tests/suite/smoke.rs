use crate::common::{hex, Rig};
use canpos_models::th::TH;

#[test]
fn boot_sdo_nmt_tpdo_smoke() {
    let mut r = Rig::new(&TH);
    let boot = r.take();
    assert_eq!(boot[0].std_id(), Some(0x77F));
    assert_eq!(boot[0].data(), &[0x00]);
    assert_eq!(
        r.req(0x67F, &hex("40 00 10 00 00 00 00 00")),
        (0x5FF, hex("43 00 10 00 96 01 08 00"))
    );
    assert!(r.send(0x000, &[0x01, 0x7F]).is_empty());
    let f = r.advance_ms(10);
    assert_eq!(
        f.iter().filter(|(_, f)| f.std_id() == Some(0x1FF)).count(),
        10
    );
}
