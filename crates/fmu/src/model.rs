//! What an FMU instance is, independent of the C ABI: its variables (one table from which both
//! `modelDescription.xml` and the value-reference checks of the glue come) and the
//! [`FmuModel`] trait each kind of instance implements. The kind is chosen from the FMU's
//! resources ([`crate::kind`]); the glue ([`crate::ffi`]) knows no kind.

/// The FMI 3.0 type of a variable (those canpos uses).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VarType {
    /// `fmi3Float64`.
    Float64,
    /// `fmi3UInt8`.
    UInt8,
    /// `fmi3UInt16`.
    UInt16,
    /// `fmi3UInt32`.
    UInt32,
    /// `fmi3UInt64`.
    UInt64,
    /// `fmi3Boolean`.
    Boolean,
    /// `fmi3Binary`.
    Binary,
    /// `fmi3Clock`.
    Clock,
}

impl VarType {
    /// The element name in `modelDescription.xml`.
    pub fn element(self) -> &'static str {
        match self {
            VarType::Float64 => "Float64",
            VarType::UInt8 => "UInt8",
            VarType::UInt16 => "UInt16",
            VarType::UInt32 => "UInt32",
            VarType::UInt64 => "UInt64",
            VarType::Boolean => "Boolean",
            VarType::Binary => "Binary",
            VarType::Clock => "Clock",
        }
    }
}

/// Value reference of the independent variable `time` every description starts with.
pub const VR_TIME: u32 = 0;

/// Causality of a variable.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Causality {
    /// The independent variable (`time`, s).
    Independent,
    /// A fixed parameter: set before the end of initialization only.
    Parameter,
    /// An input: set any time after instantiation.
    Input,
    /// An output.
    Output,
}

/// One model variable.
#[derive(Debug, Clone, PartialEq)]
pub struct Variable {
    /// Name (`CAN.Rx_Data`, `magnet_position[1]` …).
    pub name: String,
    /// Value reference.
    pub vr: u32,
    /// Type.
    pub ty: VarType,
    /// Causality.
    pub causality: Causality,
    /// Start value as written in the XML (parameters and inputs).
    pub start: Option<String>,
    /// Unit (`mm`, `degC`, `kbit/s`).
    pub unit: Option<&'static str>,
    /// Description shown by importers.
    pub description: String,
    /// Value reference of the clock of a clocked variable (`Rx_Data` → `Rx_Clock`).
    pub clocks: Option<u32>,
    /// `mimeType` of a binary.
    pub mime_type: Option<&'static str>,
    /// `maxSize` of a binary, bytes: the bound of what the glue accepts in `fmi3SetBinary`.
    pub max_size: Option<usize>,
}

impl Variable {
    /// A variable with no start, unit, clock or MIME type.
    pub fn new(
        name: impl Into<String>,
        vr: u32,
        ty: VarType,
        causality: Causality,
        description: impl Into<String>,
    ) -> Self {
        Variable {
            name: name.into(),
            vr,
            ty,
            causality,
            start: None,
            unit: None,
            description: description.into(),
            clocks: None,
            mime_type: None,
            max_size: None,
        }
    }

    /// The independent variable `time` (value reference [`VR_TIME`]).
    pub fn time() -> Self {
        Variable::new(
            "time",
            VR_TIME,
            VarType::Float64,
            Causality::Independent,
            "simulation time",
        )
        .unit("s")
    }

    /// With a start value.
    pub fn start(mut self, s: impl Into<String>) -> Self {
        self.start = Some(s.into());
        self
    }

    /// With a unit.
    pub fn unit(mut self, u: &'static str) -> Self {
        self.unit = Some(u);
        self
    }
}

/// An FMI-LS-BUS network terminal: four variables by their member names.
#[derive(Debug, Clone, PartialEq)]
pub struct BusTerminal {
    /// Terminal name (`CAN`, `Node1` …), the prefix of its variables' names.
    pub name: String,
}

impl BusTerminal {
    /// The member names, in the order their variables are declared.
    pub const MEMBERS: [&'static str; 4] = ["Rx_Data", "Tx_Data", "Rx_Clock", "Tx_Clock"];
}

/// Everything `modelDescription.xml`, `terminalsAndIcons.xml` and the manifest say about one
/// FMU, and what the glue checks calls against.
#[derive(Debug, Clone)]
pub struct Description {
    /// `modelName`.
    pub model_name: String,
    /// `modelIdentifier`: the shared library's file name without `.so`.
    pub model_identifier: String,
    /// `description`.
    pub description: String,
    /// `instantiationToken`.
    pub token: String,
    /// The variables, ordered by value reference.
    pub variables: Vec<Variable>,
    /// The LS-BUS terminals.
    pub terminals: Vec<BusTerminal>,
    /// The manifest's `isBusSimulationFMU`.
    pub is_bus_simulation: bool,
    /// Files under `documentation/` (name, contents), e.g. the unit's EDS.
    pub documentation: Vec<(String, String)>,
    /// `DefaultExperiment` step size, s.
    pub step_size: f64,
}

impl Description {
    /// The variable with value reference `vr`.
    pub fn variable(&self, vr: u32) -> Option<&Variable> {
        self.variables
            .binary_search_by_key(&vr, |v| v.vr)
            .ok()
            .map(|i| &self.variables[i])
    }
}

/// A value handed to or taken from an instance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Value<'a> {
    /// `fmi3Float64`.
    Float64(f64),
    /// `fmi3UInt8`.
    UInt8(u8),
    /// `fmi3UInt16`.
    UInt16(u16),
    /// `fmi3UInt32`.
    UInt32(u32),
    /// `fmi3UInt64`.
    UInt64(u64),
    /// `fmi3Boolean`.
    Boolean(bool),
    /// `fmi3Binary`: borrowed from the caller (set) or from the instance (get; valid until the
    /// next call on the instance).
    Binary(&'a [u8]),
    /// `fmi3Clock`: active or not.
    Clock(bool),
}

/// What a step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepResult {
    /// The instance has something for event mode (an output clock ticked).
    pub event_needed: bool,
    /// Where it stopped, s (the step's end unless it returned early).
    pub last_time: f64,
    /// It returned before the step's end.
    pub early_return: bool,
}

/// The results of `fmi3UpdateDiscreteStates`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Discrete {
    /// Call again at the same time (an output clock ticked during this update).
    pub need_update: bool,
    /// Time of the next time event, if known.
    pub next_event_time: Option<f64>,
}

/// An instance of one kind of canpos FMU, behind the FMI glue. Every method gets checked
/// arguments (the variable exists, has this type and may be set now; times move forward) and
/// answers with a reason the glue logs on error. Nothing here may panic on a caller's input.
pub trait FmuModel: Send {
    /// The description the instance was made from.
    fn description(&self) -> &Description;
    /// `fmi3EnterInitializationMode` at `start_time`.
    fn enter_initialization(&mut self, start_time: f64) -> Result<(), String>;
    /// `fmi3ExitInitializationMode`: parameters are fixed from now on.
    fn exit_initialization(&mut self) -> Result<(), String>;
    /// Reads a variable (its type was checked).
    fn get(&mut self, vr: u32) -> Result<Value<'_>, String>;
    /// Writes a variable (its type, causality and the mode were checked).
    fn set(&mut self, vr: u32, v: Value<'_>) -> Result<(), String>;
    /// `fmi3DoStep` from `t` by `h` (s): runs on the simulation clock, never the wall clock.
    fn do_step(&mut self, t: f64, h: f64, early_return_allowed: bool)
        -> Result<StepResult, String>;
    /// `fmi3EnterEventMode`.
    fn enter_event_mode(&mut self) -> Result<(), String> {
        Ok(())
    }
    /// `fmi3UpdateDiscreteStates`: takes the input clocks set in this event.
    fn update_discrete_states(&mut self) -> Result<Discrete, String>;
    /// `fmi3EnterStepMode`: output clocks and what they carried are done with.
    fn enter_step_mode(&mut self) -> Result<(), String>;
    /// Warnings the instance collected since the last call (the glue logs them).
    fn take_log(&mut self) -> Vec<String> {
        Vec::new()
    }
}
