//! The CiA 406 object rules, as [`canpos_stack::od::Hook::app`] numbers in the model tables: each
//! object names the rule that governs it, so no index list is repeated here.

/// 0x6000 operating parameters: only the code-sequence bit (D2); positions follow it.
pub const CODE_SEQUENCE: u8 = 1;
/// 0x6005/1 position measuring step (writable on TMI, R31): whole µm, not below the
/// variant's minimum; positions follow it.
pub const MEASURING_STEP: u8 = 2;
/// 0x6010/n preset: the current position reads the written value (SPEC §10).
pub const PRESET: u8 = 3;
/// 0x6301/n cam enable, 0x6302/n cam polarity: one bit per cam, four cams.
pub const CAM_SWITCH: u8 = 4;
/// 0x631x / 0x632x / 0x633x cam limits and hysteresis: the cam states follow.
pub const CAM_LIMIT: u8 = 5;
/// 0x6401/n, 0x6402/n work-area limits: the work-area state follows.
pub const WORK_AREA_LIMIT: u8 = 6;
/// 0x6200 cyclic timer: one value with TPDO1's event timer (D12).
pub const CYCLIC_TIMER: u8 = 7;
/// 0x6500 operating status: reads the active 0x6000 (D2).
pub const OPERATING_STATUS: u8 = 8;
/// 0x6509 offset value: reads the offset of channel 1's preset (0x650C/1).
pub const OFFSET: u8 = 9;
/// TMI 0x1002 manufacturer status register (§1.15): conditions and NMT state.
pub const MANUFACTURER_STATUS: u8 = 10;
