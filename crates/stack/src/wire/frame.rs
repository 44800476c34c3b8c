use core::fmt;

/// A classic CAN 2.0A frame as canpos sees it: 11-bit identifier, optional RTR, 0–8 data bytes.
///
/// Extended (29-bit) identifiers are carried in `id` too (`extended == true`) so that a device
/// can see and ignore them; CANopen devices never answer them.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct Frame {
    id: u32,
    extended: bool,
    rtr: bool,
    dlc: u8,
    data: [u8; 8],
}

/// Why a frame could not be built.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameError {
    /// More than 8 data bytes, or a DLC above 8.
    TooLong,
    /// Identifier does not fit 11 (standard) or 29 (extended) bits.
    BadId,
}

impl fmt::Display for FrameError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FrameError::TooLong => f.write_str("CAN frame longer than 8 bytes"),
            FrameError::BadId => f.write_str("CAN identifier out of range"),
        }
    }
}

impl Frame {
    /// A standard data frame. Panics never: `data` longer than 8 is an error.
    pub fn new(id: u16, data: &[u8]) -> Result<Self, FrameError> {
        if id > 0x7FF {
            return Err(FrameError::BadId);
        }
        Self::with_id(id as u32, false, data)
    }

    /// A data frame with a standard or extended identifier.
    pub fn with_id(id: u32, extended: bool, data: &[u8]) -> Result<Self, FrameError> {
        if data.len() > 8 {
            return Err(FrameError::TooLong);
        }
        if (!extended && id > 0x7FF) || id > 0x1FFF_FFFF {
            return Err(FrameError::BadId);
        }
        let mut d = [0u8; 8];
        d[..data.len()].copy_from_slice(data);
        Ok(Frame {
            id,
            extended,
            rtr: false,
            dlc: data.len() as u8,
            data: d,
        })
    }

    /// A remote (RTR) frame with the given DLC.
    pub fn remote(id: u32, extended: bool, dlc: u8) -> Result<Self, FrameError> {
        if dlc > 8 {
            return Err(FrameError::TooLong);
        }
        if (!extended && id > 0x7FF) || id > 0x1FFF_FFFF {
            return Err(FrameError::BadId);
        }
        Ok(Frame {
            id,
            extended,
            rtr: true,
            dlc,
            data: [0; 8],
        })
    }

    /// A standard data frame from a full 8-byte buffer; used on hot paths where the id is known good.
    #[inline]
    pub const fn std8(id: u16, data: [u8; 8]) -> Self {
        Frame {
            id: (id & 0x7FF) as u32,
            extended: false,
            rtr: false,
            dlc: 8,
            data,
        }
    }

    /// A standard data frame with the first `len` bytes of `data` (len clamped to 8).
    #[inline]
    pub const fn std_len(id: u16, data: [u8; 8], len: u8) -> Self {
        let dlc = if len > 8 { 8 } else { len };
        Frame {
            id: (id & 0x7FF) as u32,
            extended: false,
            rtr: false,
            dlc,
            data,
        }
    }

    /// A standard data frame whose `id` (≤ 0x7FF) and `dlc` (≤ 8) the caller has checked
    /// (debug builds assert it); hot paths with precomputed values.
    #[inline]
    pub(crate) const fn std_checked(id: u16, data: [u8; 8], dlc: u8) -> Self {
        debug_assert!(id <= 0x7FF && dlc <= 8);
        Frame {
            id: id as u32,
            extended: false,
            rtr: false,
            dlc,
            data,
        }
    }

    /// The identifier (11 or 29 bits).
    #[inline]
    pub const fn id(&self) -> u32 {
        self.id
    }
    /// The 11-bit identifier of a standard frame, `None` for an extended one.
    #[inline]
    pub const fn std_id(&self) -> Option<u16> {
        if self.extended {
            None
        } else {
            Some(self.id as u16)
        }
    }
    /// Whether the identifier is 29-bit.
    #[inline]
    pub const fn is_extended(&self) -> bool {
        self.extended
    }
    /// Whether this is a remote transmission request.
    #[inline]
    pub const fn is_remote(&self) -> bool {
        self.rtr
    }
    /// Data length code (0–8). For RTR frames the requested length.
    #[inline]
    pub const fn dlc(&self) -> u8 {
        self.dlc
    }
    /// The data bytes (empty for RTR frames).
    #[inline]
    pub fn data(&self) -> &[u8] {
        if self.rtr {
            &[]
        } else {
            &self.data[..self.dlc as usize]
        }
    }
    /// All 8 data bytes, zero beyond the DLC.
    #[inline]
    pub const fn raw(&self) -> &[u8; 8] {
        &self.data
    }
}

impl fmt::Debug for Frame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.extended {
            write!(f, "{:08X}", self.id)?;
        } else {
            write!(f, "{:03X}", self.id)?;
        }
        if self.rtr {
            return write!(f, "#R{}", self.dlc);
        }
        f.write_str(" [")?;
        for (i, b) in self.data().iter().enumerate() {
            if i > 0 {
                f.write_str(" ")?;
            }
            write!(f, "{b:02X}")?;
        }
        f.write_str("]")
    }
}

impl embedded_can::Frame for Frame {
    fn new(id: impl Into<embedded_can::Id>, data: &[u8]) -> Option<Self> {
        match id.into() {
            embedded_can::Id::Standard(s) => Frame::with_id(s.as_raw() as u32, false, data).ok(),
            embedded_can::Id::Extended(e) => Frame::with_id(e.as_raw(), true, data).ok(),
        }
    }

    fn new_remote(id: impl Into<embedded_can::Id>, dlc: usize) -> Option<Self> {
        if dlc > 8 {
            return None;
        }
        match id.into() {
            embedded_can::Id::Standard(s) => {
                Frame::remote(s.as_raw() as u32, false, dlc as u8).ok()
            }
            embedded_can::Id::Extended(e) => Frame::remote(e.as_raw(), true, dlc as u8).ok(),
        }
    }

    fn is_extended(&self) -> bool {
        self.extended
    }

    fn is_remote_frame(&self) -> bool {
        self.rtr
    }

    fn id(&self) -> embedded_can::Id {
        if self.extended {
            // Constructors guarantee the 29-bit range.
            embedded_can::Id::Extended(
                embedded_can::ExtendedId::new(self.id).unwrap_or(embedded_can::ExtendedId::ZERO),
            )
        } else {
            embedded_can::Id::Standard(
                embedded_can::StandardId::new(self.id as u16)
                    .unwrap_or(embedded_can::StandardId::ZERO),
            )
        }
    }

    fn dlc(&self) -> usize {
        self.dlc as usize
    }

    fn data(&self) -> &[u8] {
        Frame::data(self)
    }
}

impl Frame {
    /// Converts any `embedded-can` frame (e.g. from a HAL driver) into a canpos frame.
    pub fn from_embedded<F: embedded_can::Frame>(f: &F) -> Option<Self> {
        let (id, ext) = match f.id() {
            embedded_can::Id::Standard(s) => (s.as_raw() as u32, false),
            embedded_can::Id::Extended(e) => (e.as_raw(), true),
        };
        if f.is_remote_frame() {
            Frame::remote(id, ext, f.dlc().min(8) as u8).ok()
        } else {
            Frame::with_id(id, ext, f.data()).ok()
        }
    }

    /// Converts into any `embedded-can` frame type.
    pub fn to_embedded<F: embedded_can::Frame>(&self) -> Option<F> {
        let id: embedded_can::Id = embedded_can::Frame::id(self);
        if self.rtr {
            F::new_remote(id, self.dlc as usize)
        } else {
            F::new(id, self.data())
        }
    }
}
