//! Scenario files (`canpos scenario FILE.toml`): parsing and every check, before anything
//! starts. Each problem is reported as `FILE:LINE: what`, at the key it concerns.

use std::collections::HashMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, Result};
use canpos_host::control::Request;
use serde::Deserialize;

use crate::common;
use crate::limits;
use crate::sensor::{self, Built, SensorOpts};

/// Most nodes on one CAN bus (node-ids 1…127).
pub const MAX_NODES: usize = 127;

/// A scenario file.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Bus URL (default: the default socketcand URL).
    pub bus: Option<String>,
    /// Bus bit rate, kbit/s.
    pub bus_bitrate: Option<u32>,
    /// State directory.
    pub state_dir: Option<PathBuf>,
    /// Control interface address.
    pub control: Option<String>,
    /// Stop after this many seconds (default: run until Ctrl-C).
    pub duration: Option<f64>,
    /// The sensors.
    #[serde(default, rename = "sensor")]
    pub sensors: Vec<SensorOpts>,
    /// Timed events: control requests at a time.
    #[serde(default, rename = "event")]
    pub events: Vec<Event>,
}

/// A timed event: a control request sent `at` seconds after the start.
#[derive(Debug, Deserialize)]
pub struct Event {
    /// Seconds after the start.
    pub at: f64,
    /// The request (same fields as the control interface).
    #[serde(flatten)]
    pub request: Request,
}

/// A checked scenario: the file's values, the bus bit rate in kbit/s, and the located warnings
/// (`FILE:LINE: …`) for the caller to print.
pub struct Checked {
    /// The file as parsed (sensors and events checked).
    pub scenario: Scenario,
    /// The bus bit rate, kbit/s, checked against the CiA table.
    pub bus_bitrate: Option<u32>,
    /// `FILE:LINE: warning` lines.
    pub warnings: Vec<String>,
}

/// One step of a path into the document: a key or an array index.
#[derive(Clone, Copy, Debug)]
enum Seg<'a> {
    Key(&'a str),
    Idx(usize),
}

/// Finds the lines of keys in the file, for messages.
struct Locator<'t> {
    text: &'t str,
    doc: Option<toml_edit::ImDocument<&'t str>>,
    file: String,
}

impl<'t> Locator<'t> {
    fn new(text: &'t str, path: &Path) -> Self {
        Locator {
            text,
            doc: toml_edit::ImDocument::parse(text).ok(),
            file: path.display().to_string(),
        }
    }

    fn line_at(&self, offset: usize) -> usize {
        let end = offset.min(self.text.len());
        self.text.as_bytes()[..end]
            .iter()
            .filter(|&&b| b == b'\n')
            .count()
            + 1
    }

    /// The span of the item at `path`, or of the deepest item on the way that has one.
    fn span(&self, path: &[Seg]) -> Option<Range<usize>> {
        let doc = self.doc.as_ref()?;
        let mut node = Node::Table(doc.as_table());
        let mut best = None;
        for seg in path {
            let next = match (node, *seg) {
                (Node::Table(t), Seg::Key(k)) => {
                    if let Some(sp) = t.key(k).and_then(|k| k.span()) {
                        best = Some(sp);
                    }
                    t.get(k).map(Node::Item)
                }
                (Node::Table(_), Seg::Idx(_)) => None,
                (Node::Item(toml_edit::Item::ArrayOfTables(a)), Seg::Idx(i)) => {
                    a.get(i).map(Node::Table)
                }
                (Node::Item(it), Seg::Key(k)) => it.get(k).map(Node::Item),
                (Node::Item(it), Seg::Idx(i)) => it.get(i).map(Node::Item),
            };
            let Some(n) = next else { break };
            if let Some(sp) = n.span() {
                best = Some(sp);
            }
            node = n;
        }
        best
    }

    /// `FILE:LINE: message` (or `FILE: message` when the place is unknown).
    fn at(&self, path: &[Seg], message: impl std::fmt::Display) -> String {
        match self.span(path) {
            Some(sp) => format!("{}:{}: {message}", self.file, self.line_at(sp.start)),
            None => format!("{}: {message}", self.file),
        }
    }
}

/// A place in the parsed document: tables of an array of tables are no `Item`s of their own.
#[derive(Clone, Copy)]
enum Node<'a> {
    Item(&'a toml_edit::Item),
    Table(&'a toml_edit::Table),
}

impl Node<'_> {
    fn span(self) -> Option<Range<usize>> {
        match self {
            Node::Item(i) => i.span(),
            Node::Table(t) => t.span(),
        }
    }
}

/// Reads and checks a scenario file. `state_dir` (the command line's) overrides the file's.
pub fn load(path: &Path, state_dir: Option<PathBuf>) -> Result<(Checked, Vec<Built>)> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| anyhow!("cannot read {}: {e}", path.display()))?;
    check(&text, path, state_dir)
}

/// [`load`] on text already read (`path` names it in messages).
pub fn check(text: &str, path: &Path, state_dir: Option<PathBuf>) -> Result<(Checked, Vec<Built>)> {
    let loc = Locator::new(text, path);
    let sc: Scenario = toml::from_str(text).map_err(|e| {
        let msg = e.message().trim_end().replace('\n', "; ");
        match e.span() {
            Some(sp) => anyhow!("{}:{}: {msg}", loc.file, loc.line_at(sp.start)),
            None => anyhow!("{}: {msg}", loc.file),
        }
    })?;
    let mut warnings = Vec::new();
    let state_dir = state_dir
        .or_else(|| sc.state_dir.clone())
        .unwrap_or_else(canpos_host::runtime::default_state_dir);
    if sc.sensors.is_empty() {
        return Err(anyhow!("{}: no [[sensor]] defined", loc.file));
    }
    if sc.sensors.len() > MAX_NODES {
        return Err(anyhow!(loc.at(
            &[Seg::Key("sensor"), Seg::Idx(MAX_NODES)],
            format!(
                "{} sensors on one bus; a CAN bus carries at most {MAX_NODES} nodes",
                sc.sensors.len()
            )
        )));
    }
    if let Some(d) = sc.duration {
        limits::check_seconds(d, true)
            .map_err(|e| anyhow!(loc.at(&[Seg::Key("duration")], format!("duration: {e}"))))?;
    }
    let bus_bitrate = match sc.bus_bitrate {
        Some(b) => Some(
            common::parse_bitrate(&b.to_string())
                .map_err(|e| anyhow!(loc.at(&[Seg::Key("bus_bitrate")], e)))?,
        ),
        None => None,
    };
    // Sensors: each built (checks the values against its model), then the bus-wide checks.
    let mut built = Vec::new();
    let mut node_ids: HashMap<u8, usize> = HashMap::new();
    let mut files: HashMap<PathBuf, usize> = HashMap::new();
    for (i, s) in sc.sensors.iter().enumerate() {
        let here = |key: &'static str| [Seg::Key("sensor"), Seg::Idx(i), Seg::Key(key)];
        let b = sensor::build_setup(s, &state_dir).map_err(|e| {
            anyhow!(loc.at(
                &here(e.field.unwrap_or("model")),
                format!("sensor {i}: {e}")
            ))
        })?;
        for w in &b.warnings {
            warnings.push(loc.at(&here(w.field), format!("sensor {i}: {}", w.message)));
        }
        let id = b.setup.cfg.node_id;
        if id != 255 {
            if let Some(prev) = node_ids.insert(id, i) {
                return Err(anyhow!(loc.at(
                    &here("node_id"),
                    format!("sensor {i}: node-id {id} is already sensor {prev}'s; every node on a bus needs its own node-id")
                )));
            }
        }
        let file = b.setup.storage.path().to_path_buf();
        if let Some(prev) = files.insert(file.clone(), i) {
            return Err(anyhow!(loc.at(
                &here("serial"),
                format!(
                    "sensor {i}: would share the state file {} with sensor {prev}; give each sensor its own serial",
                    file.display()
                )
            )));
        }
        built.push(b);
    }
    // Events: values, then what they address.
    for (k, e) in sc.events.iter().enumerate() {
        let here = |key: &'static str| [Seg::Key("event"), Seg::Idx(k), Seg::Key(key)];
        limits::check_seconds(e.at, false)
            .map_err(|m| anyhow!(loc.at(&here("at"), format!("event {k}: at: {m}"))))?;
        e.request
            .validate()
            .map_err(|m| anyhow!(loc.at(&here("cmd"), format!("event {k}: {m}"))))?;
        let si = e.request.sensor().unwrap_or(0);
        let Some(b) = built.get(si) else {
            return Err(anyhow!(loc.at(
                &here("sensor"),
                format!(
                    "event {k}: sensor {si} does not exist (the file has {} sensor(s), numbered from 0)",
                    built.len()
                )
            )));
        };
        let channels = usize::from(b.setup.cfg.channels.max(1));
        match &e.request {
            Request::Magnet { index, .. } if *index >= channels => {
                return Err(anyhow!(loc.at(
                    &here("index"),
                    format!(
                        "event {k}: magnet {index} does not exist: sensor {si} has {channels} channel(s), numbered 0…{}",
                        channels - 1
                    )
                )));
            }
            Request::Motion { spec, .. } => {
                let n = spec.split(';').count();
                if n > channels {
                    return Err(anyhow!(loc.at(
                        &here("spec"),
                        format!("event {k}: {n} profiles for sensor {si}'s {channels} channel(s)")
                    )));
                }
            }
            Request::Fault {
                name,
                channel: Some(ch),
                ..
            } if (name == "missing-magnet" && *ch >= channels)
                || (name == "magnets-too-close" && *ch + 1 >= channels) =>
            {
                return Err(anyhow!(loc.at(
                    &here("channel"),
                    format!("event {k}: channel {ch} is out of range for sensor {si}'s {channels} channel(s)")
                )));
            }
            _ => {}
        }
        if let Some(d) = sc.duration {
            if e.at > d {
                warnings.push(loc.at(
                    &here("at"),
                    format!(
                        "event {k} at {} s comes after the end (duration {d} s); it never runs",
                        e.at
                    ),
                ));
            }
        }
    }
    Ok((
        Checked {
            scenario: sc,
            bus_bitrate,
            warnings,
        },
        built,
    ))
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    #[test]
    fn example_scenario_parses() {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples/scenario.toml");
        let dir = tempfile::tempdir().unwrap();
        let (checked, built) = crate::scenario::load(&p, Some(dir.path().into())).unwrap();
        assert!(checked.scenario.sensors.len() >= 2);
        assert!(!checked.scenario.events.is_empty());
        assert_eq!(built.len(), checked.scenario.sensors.len());
        assert_eq!(checked.warnings, Vec::<String>::new());
    }
}
