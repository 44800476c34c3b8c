//! Writing an FMU: `modelDescription.xml`, `terminalsAndIcons/terminalsAndIcons.xml`, the
//! FMI-LS-BUS layered-standard manifest, `documentation/`, `resources/canpos-fmu.txt` and
//! `binaries/x86_64-linux/<modelIdentifier>.so`, in a zip archive (stored, no compression:
//! the archive is written by this module, no zip library needed).

use std::fmt::Write as _;

use crate::kind::{Kind, RESOURCE_FILE};
use crate::model::{Causality, Description, VarType};

/// Where the layered standard's manifest lives in the archive.
pub const LS_BUS_MANIFEST: &str = "extra/org.fmi-standard.fmi-ls-bus/fmi-ls-manifest.xml";

fn esc(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&apos;"),
            c => o.push(c),
        }
    }
    o
}

/// `modelDescription.xml`.
pub fn model_description(d: &Description) -> String {
    let mut x = String::new();
    let _ = writeln!(x, r#"<?xml version="1.0" encoding="UTF-8"?>"#);
    let _ = writeln!(
        x,
        r#"<fmiModelDescription fmiVersion="3.0" modelName="{}" description="{}" instantiationToken="{}" generationTool="canpos {}" license="MIT OR Apache-2.0" variableNamingConvention="structured">"#,
        esc(&d.model_name),
        esc(&d.description),
        esc(&d.token),
        env!("CARGO_PKG_VERSION")
    );
    let _ = writeln!(
        x,
        r#"  <CoSimulation modelIdentifier="{}" canHandleVariableCommunicationStepSize="true" hasEventMode="true" mightReturnEarlyFromDoStep="true" canReturnEarlyAfterIntermediateUpdate="false" canBeInstantiatedOnlyOncePerProcess="false" canGetAndSetFMUState="false" canSerializeFMUState="false" providesIntermediateUpdate="false" providesEvaluateDiscreteStates="false"/>"#,
        esc(&d.model_identifier)
    );
    let units: Vec<&str> = {
        let mut u: Vec<&str> = d.variables.iter().filter_map(|v| v.unit).collect();
        u.sort_unstable();
        u.dedup();
        u
    };
    if !units.is_empty() {
        x.push_str("  <UnitDefinitions>\n");
        for u in units {
            let base = match u {
                "mm" => r#"<BaseUnit m="1" factor="0.001"/>"#,
                "degC" => r#"<BaseUnit K="1" offset="273.15"/>"#,
                "s" => r#"<BaseUnit s="1"/>"#,
                _ => "",
            };
            let _ = writeln!(x, r#"    <Unit name="{}">{base}</Unit>"#, esc(u));
        }
        x.push_str("  </UnitDefinitions>\n");
    }
    let _ = writeln!(
        x,
        r#"  <DefaultExperiment startTime="0" stepSize="{}"/>"#,
        d.step_size
    );
    x.push_str("  <ModelVariables>\n");
    for v in &d.variables {
        let causality = match v.causality {
            Causality::Parameter => "parameter",
            Causality::Input => "input",
            Causality::Output => "output",
            Causality::Independent => "independent",
        };
        let variability = match (v.causality, v.ty) {
            (Causality::Parameter, _) => "fixed",
            (Causality::Independent, _) => "continuous",
            (_, VarType::Float64) => "continuous",
            _ => "discrete",
        };
        let mut attrs = format!(
            r#"name="{}" valueReference="{}" description="{}" causality="{causality}" variability="{variability}""#,
            esc(&v.name),
            v.vr,
            esc(&v.description)
        );
        if let Some(c) = v.clocks {
            let _ = write!(attrs, r#" clocks="{c}""#);
        }
        if let Some(m) = v.mime_type {
            let _ = write!(attrs, r#" mimeType="{}""#, esc(m));
        }
        if let Some(m) = v.max_size {
            let _ = write!(attrs, r#" maxSize="{m}""#);
        }
        if let Some(u) = v.unit {
            let _ = write!(attrs, r#" unit="{}""#, esc(u));
        }
        if v.ty == VarType::Clock {
            let _ = write!(attrs, r#" intervalVariability="triggered""#);
        }
        match (&v.start, v.ty) {
            (Some(s), VarType::Binary) => {
                let _ = writeln!(
                    x,
                    r#"    <Binary {attrs}><Start value="{}"/></Binary>"#,
                    esc(s)
                );
            }
            (Some(s), t) => {
                let _ = writeln!(x, r#"    <{} {attrs} start="{}"/>"#, t.element(), esc(s));
            }
            (None, t) => {
                let _ = writeln!(x, r#"    <{} {attrs}/>"#, t.element());
            }
        }
    }
    x.push_str("  </ModelVariables>\n  <ModelStructure>\n");
    let outputs: Vec<_> = d
        .variables
        .iter()
        .filter(|v| v.causality == Causality::Output)
        .collect();
    for v in &outputs {
        let _ = writeln!(x, r#"    <Output valueReference="{}"/>"#, v.vr);
    }
    // fmpy wants the output clocks among the initial unknowns; they and the outputs are
    // known once initialization ends.
    for v in outputs.iter().filter(|v| v.clocks.is_none()) {
        let _ = writeln!(x, r#"    <InitialUnknown valueReference="{}"/>"#, v.vr);
    }
    x.push_str("  </ModelStructure>\n</fmiModelDescription>\n");
    x
}

/// `terminalsAndIcons/terminalsAndIcons.xml`: one LS-BUS network terminal per bus terminal.
pub fn terminals_and_icons(d: &Description) -> String {
    let mut x = String::from(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<fmiTerminalsAndIcons fmiVersion=\"3.0\">\n  <Terminals>\n",
    );
    for t in &d.terminals {
        let _ = writeln!(
            x,
            r#"    <Terminal name="{}" terminalKind="org.fmi-ls-bus.network-terminal" matchingRule="org.fmi-ls-bus.transceiver">"#,
            esc(&t.name)
        );
        for m in crate::model::BusTerminal::MEMBERS {
            let _ = writeln!(
                x,
                r#"      <TerminalMemberVariable variableName="{}.{m}" memberName="{m}" variableKind="signal"/>"#,
                esc(&t.name)
            );
        }
        x.push_str("    </Terminal>\n");
    }
    x.push_str("  </Terminals>\n</fmiTerminalsAndIcons>\n");
    x
}

/// The FMI-LS-BUS layered-standard manifest.
pub fn ls_bus_manifest(d: &Description) -> String {
    format!(
        r#"<?xml version="1.0" encoding="UTF-8"?>
<fmiLayeredStandardManifest xmlns:fmi-ls="http://fmi-standard.org/fmi-ls-manifest" fmi-ls:fmi-ls-name="org.fmi-standard.fmi-ls-bus" fmi-ls:fmi-ls-version="1.0.0" fmi-ls:fmi-ls-description="Layered Standard for the simulation of bus communication on a Physical Signal Abstraction or Network Abstraction based level." isBusSimulationFMU="{}"/>
"#,
        d.is_bus_simulation
    )
}

/// The archive's members, in order (name, contents).
pub fn members(kind: &Kind, library: &[u8]) -> Result<Vec<(String, Vec<u8>)>, String> {
    let d = kind.description()?;
    let mut m = vec![
        (
            "modelDescription.xml".to_string(),
            model_description(&d).into_bytes(),
        ),
        (
            "terminalsAndIcons/terminalsAndIcons.xml".to_string(),
            terminals_and_icons(&d).into_bytes(),
        ),
        (
            LS_BUS_MANIFEST.to_string(),
            ls_bus_manifest(&d).into_bytes(),
        ),
        (
            format!("resources/{RESOURCE_FILE}"),
            kind.resource_text().into_bytes(),
        ),
    ];
    for (name, text) in &d.documentation {
        m.push((format!("documentation/{name}"), text.clone().into_bytes()));
    }
    m.push((
        format!("binaries/x86_64-linux/{}.so", d.model_identifier),
        library.to_vec(),
    ));
    Ok(m)
}

/// A zip archive of `members`, stored (method 0), with fixed times so that the same inputs give
/// the same bytes.
pub fn zip(members: &[(String, Vec<u8>)]) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    let mut central = Vec::new();
    // 1980-01-01 00:00 in DOS time.
    let (time, date) = (0u16, (1 << 5) | 1u16);
    for (name, data) in members {
        let (Ok(size), Ok(offset), Ok(nlen)) = (
            u32::try_from(data.len()),
            u32::try_from(out.len()),
            u16::try_from(name.len()),
        ) else {
            return Err(format!("{name}: too large for a zip archive without zip64"));
        };
        let crc = canpos_stack::storage::crc32(data);
        let common = |v: &mut Vec<u8>| {
            v.extend_from_slice(&20u16.to_le_bytes()); // version needed
            v.extend_from_slice(&0u16.to_le_bytes()); // flags
            v.extend_from_slice(&0u16.to_le_bytes()); // stored
            v.extend_from_slice(&time.to_le_bytes());
            v.extend_from_slice(&date.to_le_bytes());
            v.extend_from_slice(&crc.to_le_bytes());
            v.extend_from_slice(&size.to_le_bytes());
            v.extend_from_slice(&size.to_le_bytes());
            v.extend_from_slice(&nlen.to_le_bytes());
            v.extend_from_slice(&0u16.to_le_bytes()); // extra
        };
        out.extend_from_slice(&0x0403_4b50u32.to_le_bytes());
        common(&mut out);
        out.extend_from_slice(name.as_bytes());
        out.extend_from_slice(data);
        central.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
        central.extend_from_slice(&(0x0300u16 | 20).to_le_bytes()); // made by: Unix
        common(&mut central);
        central.extend_from_slice(&0u16.to_le_bytes()); // comment
        central.extend_from_slice(&0u16.to_le_bytes()); // disk
        central.extend_from_slice(&0u16.to_le_bytes()); // internal attributes
        let mode: u32 = if name.ends_with(".so") {
            0o100755
        } else {
            0o100644
        };
        central.extend_from_slice(&(mode << 16).to_le_bytes());
        central.extend_from_slice(&offset.to_le_bytes());
        central.extend_from_slice(name.as_bytes());
    }
    let (Ok(cd_off), Ok(cd_len), Ok(n)) = (
        u32::try_from(out.len()),
        u32::try_from(central.len()),
        u16::try_from(members.len()),
    ) else {
        return Err("the archive is too large for a zip archive without zip64".into());
    };
    out.extend_from_slice(&central);
    out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    out.extend_from_slice(&[0, 0, 0, 0]);
    out.extend_from_slice(&n.to_le_bytes());
    out.extend_from_slice(&n.to_le_bytes());
    out.extend_from_slice(&cd_len.to_le_bytes());
    out.extend_from_slice(&cd_off.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    Ok(out)
}

/// The FMU of `kind` with `library` (the bytes of `libcanpos_fmu.so`) as its binary.
pub fn fmu(kind: &Kind, library: &[u8]) -> Result<Vec<u8>, String> {
    zip(&members(kind, library)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_description_names_every_variable_once_and_the_terminal() {
        let k = Kind::from_resource("kind = sensor\nmodel = th").unwrap();
        let d = k.description().unwrap();
        let md = model_description(&d);
        for v in &d.variables {
            assert_eq!(
                md.matches(&format!("valueReference=\"{}\" ", v.vr)).count(),
                1,
                "{}",
                v.name
            );
        }
        assert!(md.contains(r#"hasEventMode="true""#));
        assert!(md.contains(&d.token));
        let t = terminals_and_icons(&d);
        assert!(
            t.contains(r#"variableName="CAN.Tx_Clock" memberName="Tx_Clock""#),
            "{t}"
        );
        assert!(ls_bus_manifest(&d).contains(r#"isBusSimulationFMU="false""#));
        let mut vrs: Vec<u32> = d.variables.iter().map(|v| v.vr).collect();
        vrs.dedup();
        assert_eq!(vrs.len(), d.variables.len());
        assert!(vrs.windows(2).all(|w| w[0] < w[1]), "sorted: {vrs:?}");
    }

    #[test]
    fn the_zip_has_its_members_with_their_crc() {
        let z = zip(&[("a.txt".into(), b"hello".to_vec()), ("b/c".into(), vec![])]).unwrap();
        assert_eq!(&z[..4], b"PK\x03\x04");
        assert_eq!(
            u32::from_le_bytes(z[14..18].try_into().unwrap()),
            0x3610_A686
        );
        assert_eq!(&z[z.len() - 22..z.len() - 18], b"PK\x05\x06");
        assert_eq!(
            u16::from_le_bytes(z[z.len() - 12..z.len() - 10].try_into().unwrap()),
            2
        );
    }
}
