//! The application a node runs: what the CiA 301 / 305 stack hands on for the objects and
//! events it does not own itself.
//!
//! The stack (NMT, SDO, PDO, EMCY, error control, storage, LSS) knows no device profile and no
//! product. An object in the model's table whose hook is [`crate::od::Hook::app`] belongs to
//! the application: the stack asks it to [`Application::validate`] a write, tells it what was
//! [`Application::written`], lets it [`Application::refresh`] a derived value before a read,
//! and runs its [`Application::cycle`] with each process sample. A device profile's application
//! (canpos-encoder's CiA 406 encoder) lives in a crate above this one; [`Plain`] is a CiA 301
//! device with no application of its own (every object a plain value).

use crate::emcy::Emcy;
use crate::model::{Features, Model, UnitConfig};
use crate::nmt::NmtState;
use crate::od::{Abort, Dictionary};
use crate::pdo::Tpdos;
use crate::wire::Instant;

/// What the application may touch while it runs a cycle or reacts to a write.
pub struct AppCtx<'a, A: Application + ?Sized> {
    /// The dictionary (live values are written here).
    pub od: &'a mut Dictionary,
    /// EMCY producer.
    pub emcy: &'a mut Emcy,
    /// TPDOs (told about changed mapped values).
    pub pdo: &'a mut Tpdos,
    /// The device description the node runs.
    pub model: &'static ModelOf<A>,
    /// The unit configuration ([`Application::Config`]).
    pub cfg: &'a A::Config,
    /// The NMT state (an application may report it in an object of its own).
    pub nmt: NmtState,
    /// Active bit rate in kbit/s, 0 while autobaud has not locked (TMI R27 check).
    pub bitrate_kbps: u16,
    /// Current time.
    pub now: Instant,
}

/// Read-only view for write validation.
pub struct AppView<'a, A: Application + ?Sized> {
    /// The dictionary.
    pub od: &'a Dictionary,
    /// The device description the node runs.
    pub model: &'static ModelOf<A>,
    /// The unit configuration.
    pub cfg: &'a A::Config,
}

/// The application side of a node. Every method has the default "nothing to do", so an
/// application implements only what it owns.
pub trait Application {
    /// One process cycle's input (a measurement).
    type Sample;
    /// A fault the application reports the way its device's manual says.
    type Fault: Copy;

    /// The unit configuration the application reads (the stack reads [`UnitConfig`] of it).
    type Config: UnitConfig;
    /// What the application's device descriptions add to the stack's ([`Model::profile`]).
    type Profile: 'static;

    /// The device description the build fixes: a firmware for a device of its own, as
    /// CANopenNode's `CO_config.h` fixes its services. It must be the node's model (or one of
    /// its unit variants with the same features); the node and the application then take its
    /// features as constants and link no branch for a feature the device lacks. `None` (the
    /// default): read from the node's model.
    const FIXED: Option<&'static ModelOf<Self>> = None;

    /// The features of a node of `model` running this application: [`Application::FIXED`]'s
    /// when the build fixes them, else `model`'s.
    #[inline(always)]
    fn features(model: &'static ModelOf<Self>) -> &'static Features {
        match Self::FIXED {
            Some(f) => {
                debug_assert!(
                    f.features.tag == model.features.tag,
                    "FEATURES are the model's"
                );
                &f.features
            }
            None => &model.features,
        }
    }

    /// The profile part of `model`'s description, [`Application::FIXED`]'s when fixed.
    #[inline(always)]
    fn profile(model: &'static ModelOf<Self>) -> &'static Self::Profile {
        match Self::FIXED {
            Some(f) => &f.profile,
            None => &model.profile,
        }
    }

    /// Power-on: back to the state of a device that was just switched on.
    fn power_on(&mut self) {}

    /// NMT reset node: forgets runtime state (what only a power cycle clears stays).
    fn reset(&mut self) {}

    /// Runs one process cycle. Returns true when the device's reaction forces the node back to
    /// pre-operational.
    fn cycle(&mut self, _s: &Self::Sample, _cx: &mut AppCtx<'_, Self>) -> bool {
        false
    }

    /// Injects (`active`) or removes a fault. Returns true when the device's reaction forces
    /// the node back to pre-operational.
    fn inject(&mut self, _f: Self::Fault, _active: bool, _cx: &mut AppCtx<'_, Self>) -> bool {
        false
    }

    /// The rule of application hook `h` for a write of `raw` to sub-index `sub`.
    fn validate(&self, _h: u8, _sub: u8, _raw: u32, _cx: &AppView<'_, Self>) -> Result<(), Abort> {
        Ok(())
    }

    /// The side effects of application hook `h` once `raw` was written to `sub`.
    fn written(&mut self, _h: u8, _sub: u8, _raw: u32, _cx: &mut AppCtx<'_, Self>) {}

    /// Communication parameter `sub` of TPDO `n` changed (an application may keep an object
    /// of its own in step, such as CiA 406's cyclic timer 0x6200).
    fn tpdo_comm_written(&mut self, _n: usize, _sub: u8, _raw: u32, _cx: &mut AppCtx<'_, Self>) {}

    /// Brings a value the application derives (hook `h`) up to date before it is read.
    fn refresh(&self, _h: u8, _od: &mut Dictionary, _nmt: NmtState) {}

    /// The application's value `k` (< [`crate::storage::APP_RECORDS`]) that is no object but is
    /// stored with the application parameters: a "save" of them (0x1010 sub 1 or 3) stores it,
    /// a "load" forgets it, and reset node gives it back through [`Application::load_stored`].
    /// `None`: nothing to store (CiA 406's preset offset of a device without an offset object,
    /// the TMI, is the one user).
    fn stored_value(&self, _k: usize) -> Option<u32> {
        None
    }

    /// Reset node and power-on, after [`Application::reset`]: the stored value `k` (see
    /// [`Application::stored_value`]); not called for a value that is not stored.
    fn load_stored(&mut self, _k: usize, _v: u32) {}

    /// Whether values of the automatically stored group changed since the last call (the node
    /// then persists them).
    fn take_auto_dirty(&mut self) -> bool {
        false
    }

    /// Whether the application refuses an NMT start now (it raises its own EMCY if so).
    fn refuses_start(&self, _emcy: &mut Emcy) -> bool {
        false
    }

    /// The stored data failed its check at power-on. Returns true when the application reports
    /// that itself; otherwise the node raises the generic EMCY 0x6300.
    fn storage_corrupt(&mut self, _cx: &mut AppCtx<'_, Self>) -> bool {
        false
    }
}

/// The device description of a node running `A`.
pub type ModelOf<A> = Model<<A as Application>::Config, <A as Application>::Profile>;

/// A CiA 301 device with no application of its own: every object is a plain value (a device
/// served from an EDS file).
#[derive(Clone, Copy, Debug, Default)]
pub struct Plain;

impl Application for Plain {
    type Sample = ();
    type Fault = core::convert::Infallible;
    type Config = crate::model::CommConfig;
    type Profile = ();
}
