//! Order-code parsing for the three products.
//!
//! Whitespace is ignored and letters may be given in any case, so `"EP0 0600M D34 1 C304 2 4 1
//! Z02"` and `"ep00600md341c304241z02"` are the same code. Every field is checked against what
//! its manual lists; an error names the field, its value, its box (1-based position in the
//! whitespace-free code), the rule and the manual section, e.g. `stroke length 1503M (box 4):
//! non-standard strokes are encoded in 5 mm increments (000 §3.1)`. The schemes field by field,
//! with the choices canpos made where a manual is unclear, are in docs/ORDER_CODES.md.
//!
//! # Temposonics TH (000 §3.1)
//!
//! ```text
//! box   1-2  3  4-8    9-11  12  13  14  15  16-19  20    21   22    [23-25]
//!       T H  b  cccc M  ddd  e   f   g   h   C304   baud  res  perf  [Z0n]
//! ```
//!
//! * b design: `F G M N S T W` (Table 1 flange types);
//! * c stroke: 4 digits + `M` (0025…7620 mm, in 5 mm increments) or 4 digits (tenths) /
//!   `ddd.d` + `U` (001.0…300.0 in., in 0.1 in. increments);
//! * d connection: `C01 C10 N01 N10` (all versions), `M01 M10 NF1` (versions E and N only);
//! * e operating voltage `1` (+24 VDC); f version `D E G N`; g functional safety `N`;
//!   h additional option `N`;
//! * output `C`, protocol `304` (CANopen); baud `1` 1000, `2` 500, `3` 250, `4` 125 kbit/s;
//!   resolution `1` 5 µm, `2` 2 µm; performance `1` standard;
//! * optional `Z02`…`Z04`: 2…4 magnets (multi-position), otherwise 1.
//!
//! # Temposonics E-Series EP / EL / EH (001 §3.1–3.3)
//!
//! ```text
//!       a   b  c       d    e  f     g     h    i     [j]
//!       EP  0  0600M   D34  1  C304  2     4    1     [Z02]
//! ```
//!
//! * a `EP`, `EL` or `EH`; b design: `0` (EP, EL) or `K L M S F W` (EH);
//! * c stroke: 4 digits + `M` (0050…2540 mm, in 5 mm increments) or 4 digits (tenths) /
//!   `ddd.d` + `U` (002.0…100.0 in.);
//! * d connection: `D34` (M12), EH also `EH1`…`EH4`, `ET1`…`ET4` (cable);
//! * e `1` (+24 VDC); f `C304` CANopen or `C404` CANopen with duo terminator;
//! * g baud `1` 1000, `2` 500, `3` 250, `4` 125 kbit/s; h resolution `4` 10 µm, `5` 20 µm;
//!   i type `1` standard; optional j `Z02`: 2 magnets.
//!
//! # Novotechnik TMI (002 §8 "ordering code", §2.1–2.3)
//!
//! ```text
//!       TMI  rrrr  mmm  6cs  eee
//! ```
//!
//! * rrrr: defined electrical range in mm (the stroke; the manual gives no range: canpos takes
//!   0050…4500);
//! * mmm: mechanical configuration (three digits, not decoded: the manual lists none);
//! * 6cs: CANopen interface. The manual only shows it as `6xx`; canpos decides (not in the
//!   manual): c = number of position channels (`1` or `2`), s = minimum position step
//!   (`1` = 1 µm, `5` = 5 µm), matching the product-code bits 31 / 30 of 002 §1.8;
//! * eee: electrical connection: `105` 6-pin IEC 130-9 (§2.1), `106` 5-pin M12 (§2.2), `252`
//!   cable (§2.3).
//!
//! The TMI's bit rate is not part of its order code: 250 kbit/s on delivery (002 §1.2.2).

use core::fmt;

use crate::error::{Error, Result};
use crate::spec::{Model, SensorSpec, Variant};

/// A decoded order code.
#[derive(Clone, Debug, PartialEq)]
pub struct OrderCode {
    /// Product.
    pub model: Model,
    /// Housing variant.
    pub variant: Variant,
    /// Stroke length (TMI: defined electrical range) in mm. Inch codes are converted
    /// (1 in. = 25.4 mm).
    pub stroke_mm: f64,
    /// Position resolution (minimum position step) in µm.
    pub resolution_um: u32,
    /// Bit rate on delivery in kbit/s.
    pub bit_rate_kbit: u32,
    /// Number of magnets (position channels).
    pub magnets: usize,
    /// The code, upper-case, without whitespace.
    pub normalized: String,
}

impl OrderCode {
    /// The canpos model name (`"th"`, `"e-series"` or `"tmi"`).
    pub fn model_name(&self) -> &'static str {
        self.model.name()
    }

    /// The sensor specification of the ordered unit.
    pub fn sensor_spec(&self) -> Result<SensorSpec> {
        match self.model {
            Model::Th => SensorSpec::th(self.stroke_mm, self.magnets),
            Model::ESeries => SensorSpec::e_series(self.variant, self.stroke_mm, self.magnets),
            Model::Tmi => SensorSpec::tmi(self.stroke_mm, self.magnets),
        }
    }

    /// Position resolution in nm (the value of object 0x6005/1).
    pub fn resolution_nm(&self) -> u32 {
        self.resolution_um * 1000
    }
}

impl fmt::Display for OrderCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.normalized)
    }
}

impl core::str::FromStr for OrderCode {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        parse_order_code(s)
    }
}

/// Parses an order code of any of the three products (see the module documentation for the
/// formats). The product is recognised by the leading letters (`TH`, `EP`/`EL`/`EH`, `TMI`).
pub fn parse_order_code(code: &str) -> Result<OrderCode> {
    let normalized: String = code
        .chars()
        .filter(|c| !c.is_whitespace())
        .map(|c| c.to_ascii_uppercase())
        .collect();
    let mut p = Cursor {
        code: code.trim(),
        chars: normalized.chars().collect(),
        pos: 0,
        src: "",
    };
    if p.chars.is_empty() {
        return Err(p.err("the code is empty".into()));
    }
    if let Some(c) = p.chars.iter().find(|c| !c.is_ascii()) {
        return Err(p.err(format!("unexpected character '{c}'")));
    }
    let out = if normalized.starts_with("TMI") {
        parse_tmi(&mut p)
    } else if normalized.starts_with("TLM") {
        Err(p.err("TLM (profile housing) is not modelled; only TMI, TH and E-Series are".into()))
    } else if normalized.starts_with("TH") {
        parse_th(&mut p)
    } else if normalized.starts_with("EP")
        || normalized.starts_with("EL")
        || normalized.starts_with("EH")
    {
        parse_e(&mut p)
    } else {
        Err(p.err(
            "unknown product: a code starts with TH (Temposonics TH), EP/EL/EH (E-Series) or TMI"
                .into(),
        ))
    }?;
    Ok(OrderCode { normalized, ..out })
}

/// Where each scheme's rules are written; every field error cites it.
const TH_SRC: &str = "000 §3.1";
const EP_SRC: &str = "001 §3.1";
const EL_SRC: &str = "001 §3.2";
const EH_SRC: &str = "001 §3.3";
const TMI_SRC: &str = "002 §8";
/// The TMI's connection digits are in the pin-assignment sections, one per connector.
const TMI_CONNECTION_SRC: &str = "002 §2.1–2.3";

/// The strokes a scheme can be ordered with: mm codes (`ddddM`) from `mm.0` to `mm.1` in 5 mm
/// steps, inch codes (`ddddU` in tenths, or `ddd.dU`) from `tenths.0` to `tenths.1` tenths of
/// an inch (every tenth: "must be encoded in 5 mm / 0.1 in. increments").
struct StrokeRule {
    mm: (u32, u32),
    tenths: (u32, u32),
}

/// 000 §3.1: 0025…7620 mm, 001.0…300.0 in.
const TH_STROKE: StrokeRule = StrokeRule {
    mm: (25, 7620),
    tenths: (10, 3000),
};
/// 001 §3.1–3.3: 0050…2540 mm, 002.0…100.0 in.
const E_STROKE: StrokeRule = StrokeRule {
    mm: (50, 2540),
    tenths: (20, 1000),
};

/// TH connection types for versions E and N only (000 §3.1 "(Version E & N)"; §4.4: "Version
/// D & G suitable for connection types: C01, C10, N01, N10").
const TH_E_N_ONLY: &[&str] = &["M01", "M10", "NF1"];

struct Cursor<'a> {
    code: &'a str,
    chars: Vec<char>,
    pos: usize,
    /// The manual section of the scheme being read.
    src: &'static str,
}

impl Cursor<'_> {
    fn err(&self, reason: String) -> Error {
        Error::OrderCode {
            code: self.code.to_string(),
            reason,
        }
    }

    /// An error about `field`, whose text `value` starts at box `box_no`: the field, its value,
    /// the rule it breaks and where the manual says so.
    fn field_err(&self, field: &str, box_no: usize, value: &str, rule: &str) -> Error {
        self.field_err_in(field, box_no, value, rule, self.src)
    }

    fn field_err_in(
        &self,
        field: &str,
        box_no: usize,
        value: &str,
        rule: &str,
        src: &str,
    ) -> Error {
        let reason = if value.is_empty() {
            format!("{field} (box {box_no}): the code ends here; {rule} ({src})")
        } else {
            format!("{field} {value} (box {box_no}): {rule} ({src})")
        };
        self.err(reason)
    }

    /// The next `n` characters (fewer at the end of the code).
    fn peek(&self, n: usize) -> String {
        self.chars.iter().skip(self.pos).take(n).collect()
    }

    /// Takes one of `options` (all of one length) for `field`; the error lists them.
    fn choice(&mut self, field: &str, options: &[&'static str]) -> Result<&'static str> {
        self.choice_in(field, options, self.src)
    }

    fn choice_in(
        &mut self,
        field: &str,
        options: &[&'static str],
        src: &str,
    ) -> Result<&'static str> {
        let box_no = self.pos + 1;
        let width = options.first().map_or(1, |o| o.len());
        let got = self.peek(width);
        if let Some(o) = options.iter().find(|o| **o == got) {
            self.pos += width;
            return Ok(o);
        }
        let rule = match options {
            [only] => format!("only {only}"),
            _ => format!("not one of {}", options.join(", ")),
        };
        Err(self.field_err_in(field, box_no, &got, &rule, src))
    }

    /// Takes exactly `n` digits for `field`.
    fn digits(&mut self, field: &str, n: usize) -> Result<u32> {
        let box_no = self.pos + 1;
        let got = self.peek(n);
        if got.len() != n || !got.chars().all(|c| c.is_ascii_digit()) {
            return Err(self.field_err(field, box_no, &got, &format!("{n} digits")));
        }
        self.pos += n;
        got.parse()
            .map_err(|_| self.field_err(field, box_no, &got, "bad number"))
    }

    /// Parses the stroke field: `ddddM` (mm) or `ddddU` (tenths of an inch) / `ddd.dU`
    /// (inches), within `rule`. Returns mm.
    fn stroke(&mut self, rule: &StrokeRule) -> Result<f64> {
        const FIELD: &str = "stroke length";
        let start = self.pos;
        let box_no = start + 1;
        let mut text = String::new();
        while let Some(&c) = self.chars.get(self.pos) {
            if (c.is_ascii_digit() || c == '.') && text.len() < 6 {
                text.push(c);
                self.pos += 1;
            } else {
                break;
            }
        }
        let unit = self.chars.get(self.pos).copied();
        let value: String = text.chars().chain(unit).collect();
        let (lo, hi) = rule.mm;
        let (tlo, thi) = rule.tenths;
        let inches = |t: u32| format!("{:03}.{}", t / 10, t % 10);
        let number = |s: &str| s.parse::<u32>().ok();
        let tenths = match (unit, text.len(), text.find('.')) {
            (Some('M'), 4, None) => {
                let mm = number(&text).unwrap_or(0);
                self.pos += 1;
                if mm < lo || mm > hi {
                    return Err(self.field_err(
                        FIELD,
                        box_no,
                        &value,
                        &format!("outside {lo}…{hi} mm ({lo:04}M…{hi:04}M)"),
                    ));
                }
                if mm % 5 != 0 {
                    return Err(self.field_err(
                        FIELD,
                        box_no,
                        &value,
                        "non-standard strokes are encoded in 5 mm increments",
                    ));
                }
                return Ok(f64::from(mm));
            }
            (Some('U'), 4, None) => number(&text),
            (Some('U'), 5, Some(3)) => number(&text.replace('.', "")),
            _ => None,
        };
        let Some(tenths) = tenths else {
            return Err(self.field_err(
                FIELD,
                box_no,
                &value,
                "4 digits and M (mm, e.g. 0500M), or 4 digits or ddd.d and U (tenths of an \
                 inch or inches, e.g. 0200U or 020.0U)",
            ));
        };
        self.pos += 1;
        if tenths < tlo || tenths > thi {
            return Err(self.field_err(
                FIELD,
                box_no,
                &value,
                &format!("outside {}…{} in.", inches(tlo), inches(thi)),
            ));
        }
        // 0.1 in. = 2.54 mm: exact to the µm.
        Ok(f64::from(tenths) * 2540.0 / 1000.0)
    }

    fn at_end(&self) -> bool {
        self.pos >= self.chars.len()
    }

    fn expect_end(&self) -> Result<()> {
        if self.at_end() {
            Ok(())
        } else {
            let rest: String = self.chars[self.pos..].iter().collect();
            Err(self.err(format!(
                "unexpected \"{rest}\" from box {} (the code ends after its last field, {})",
                self.pos + 1,
                self.src
            )))
        }
    }
}

/// Baud-rate digit (both MTS schemes): 1 1000, 2 500, 3 250, 4 125 kbit/s.
const BAUD: &[&str] = &["1", "2", "3", "4"];

fn baud_kbit(digit: &str) -> u32 {
    match digit {
        "1" => 1000,
        "2" => 500,
        "3" => 250,
        _ => 125,
    }
}

fn parse_th(p: &mut Cursor<'_>) -> Result<OrderCode> {
    p.src = TH_SRC;
    p.choice("sensor model", &["TH"])?;
    // Table 1: F, G, W (enclosure type 3X), M, N, S, T (type 3).
    p.choice("design", &["F", "G", "M", "N", "S", "T", "W"])?;
    let stroke_mm = p.stroke(&TH_STROKE)?;
    let conn_box = p.pos + 1;
    let connection = p.choice(
        "connection type",
        &["C01", "C10", "M01", "M10", "N01", "N10", "NF1"],
    )?;
    p.choice("operating voltage", &["1"])?;
    let version_box = p.pos + 1;
    let version = p.choice("version", &["D", "E", "G", "N"])?;
    if TH_E_N_ONLY.contains(&connection) && !matches!(version, "E" | "N") {
        return Err(p.field_err(
            "connection type",
            conn_box,
            connection,
            &format!("only with versions E and N, not with version {version} (box {version_box})"),
        ));
    }
    // Boxes 14 and 15: the manual lists "N" only (not approved / none).
    p.choice("functional safety type", &["N"])?;
    p.choice("additional option type", &["N"])?;
    p.choice("output", &["C"])?;
    // Footnote 3: further CAN protocols on request; the manual lists CANopen only.
    p.choice("protocol", &["304"])?;
    let baud = p.choice("baud rate", BAUD)?;
    let res = p.choice("resolution", &["1", "2"])?;
    p.choice("performance", &["1"])?;
    let magnets = if p.at_end() {
        1
    } else {
        match p.choice("magnet number", &["Z02", "Z03", "Z04"])? {
            "Z02" => 2,
            "Z03" => 3,
            _ => 4,
        }
    };
    p.expect_end()?;
    Ok(OrderCode {
        model: Model::Th,
        variant: Variant::Th,
        stroke_mm,
        resolution_um: if res == "1" { 5 } else { 2 },
        bit_rate_kbit: baud_kbit(baud),
        magnets,
        normalized: String::new(),
    })
}

fn parse_e(p: &mut Cursor<'_>) -> Result<OrderCode> {
    p.src = "001 §3.1–3.3";
    let style = p.choice("sensor model", &["EP", "EL", "EH"])?;
    let (variant, src) = match style {
        "EP" => (Variant::Ep, EP_SRC),
        "EL" => (Variant::El, EL_SRC),
        _ => (Variant::Eh, EH_SRC),
    };
    p.src = src;
    if variant == Variant::Eh {
        p.choice("design", &["K", "L", "M", "S", "F", "W"])?;
    } else {
        // "0 Without position magnet".
        p.choice("design", &["0"])?;
    }
    let stroke_mm = p.stroke(&E_STROKE)?;
    if variant == Variant::Eh {
        p.choice(
            "connection type",
            &[
                "D34", "EH1", "EH2", "EH3", "EH4", "ET1", "ET2", "ET3", "ET4",
            ],
        )?;
    } else {
        p.choice("connection type", &["D34"])?;
    }
    p.choice("operating voltage", &["1"])?;
    p.choice("output", &["C304", "C404"])?;
    let baud = p.choice("baud rate", BAUD)?;
    let res = p.choice("resolution", &["4", "5"])?;
    p.choice("type", &["1"])?;
    let magnets = if p.at_end() {
        1
    } else {
        p.choice("magnet number", &["Z02"])?;
        2
    };
    p.expect_end()?;
    Ok(OrderCode {
        model: Model::ESeries,
        variant,
        stroke_mm,
        resolution_um: if res == "4" { 10 } else { 20 },
        bit_rate_kbit: baud_kbit(baud),
        magnets,
        normalized: String::new(),
    })
}

fn parse_tmi(p: &mut Cursor<'_>) -> Result<OrderCode> {
    p.src = TMI_SRC;
    p.choice("type", &["TMI"])?;
    let box_no = p.pos + 1;
    let range = p.digits("defined electrical range", 4)?;
    let (lo, hi) = Model::Tmi.stroke_range_mm();
    let stroke_mm = f64::from(range);
    if stroke_mm < lo || stroke_mm > hi {
        return Err(p.field_err_in(
            "defined electrical range",
            box_no,
            &format!("{range:04}"),
            &format!("outside {lo}…{hi} mm"),
            "canpos: the manual gives no range, docs/DECISIONS.md",
        ));
    }
    p.digits("mechanical configuration", 3)?;
    // "6xx" (002 §2.1–2.3); the two digits after the 6 as canpos reads them (DECISIONS.md).
    p.choice("CANopen interface", &["6"])?;
    let decided = "canpos reads 6xx as 6cs, docs/DECISIONS.md";
    let ch = p.choice_in(
        "CANopen interface: number of channels",
        &["1", "2"],
        decided,
    )?;
    let step = p.choice_in(
        "CANopen interface: minimum position step (1 or 5 µm)",
        &["1", "5"],
        decided,
    )?;
    p.choice_in(
        "electrical connection",
        &["105", "106", "252"],
        TMI_CONNECTION_SRC,
    )?;
    p.expect_end()?;
    Ok(OrderCode {
        model: Model::Tmi,
        variant: Variant::Tmi,
        stroke_mm,
        resolution_um: if step == "1" { 1 } else { 5 },
        bit_rate_kbit: 250,
        magnets: if ch == "1" { 1 } else { 2 },
        normalized: String::new(),
    })
}

#[cfg(test)]
mod tests {
    //! Table-driven from the manuals' order-code figures: every field of every scheme, every
    //! value the manual lists accepted (and decoded), every other value of the field's
    //! alphabet refused with the field, its rule and the manual section in the error. The
    //! tables here are transcribed from the manuals, not taken from the parser.
    use super::*;

    /// Letters and digits: the alphabet of a one-character box.
    const ALNUM: &str = "ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789";

    /// One field of a scheme: its name (as the errors say it), the manual section, the values
    /// the manual lists, and the candidates to try (accepted exactly when listed).
    struct Field {
        name: &'static str,
        src: &'static str,
        listed: Vec<String>,
        candidates: Vec<String>,
    }

    fn chars() -> Vec<String> {
        ALNUM.chars().map(String::from).collect()
    }

    /// Every string of `n` characters from `alphabet`.
    fn words(alphabet: &str, n: usize) -> Vec<String> {
        let mut out = vec![String::new()];
        for _ in 0..n {
            out = out
                .iter()
                .flat_map(|w| alphabet.chars().map(move |c| format!("{w}{c}")))
                .collect();
        }
        out
    }

    fn reason(code: &str) -> String {
        match parse_order_code(code) {
            Err(Error::OrderCode { reason, .. }) => reason,
            other => panic!("expected an order-code error for {code:?}, got {other:?}"),
        }
    }

    /// Replaces field `i` of `base` by `v` and returns the code.
    fn with(base: &[&str], i: usize, v: &str) -> String {
        let mut f: Vec<&str> = base.to_vec();
        f[i] = v;
        f.concat()
    }

    /// Checks every candidate of every field of a scheme (the others at `base`).
    fn check_fields(base: &[&str], fields: &[(usize, Field)]) {
        let (mut accepted, mut refused, mut unclear) = (vec![], vec![], vec![]);
        for (i, f) in fields {
            // Every listed value is among the candidates.
            assert!(
                f.listed.iter().all(|v| f.candidates.contains(v)),
                "{}",
                f.name
            );
            for v in &f.candidates {
                let code = with(base, *i, v);
                match (parse_order_code(&code), f.listed.contains(v)) {
                    (Ok(_), false) => accepted.push(format!("{} {v}: {code}", f.name)),
                    (Err(e), true) => refused.push(format!("{} {v}: {e}", f.name)),
                    (Err(Error::OrderCode { reason, .. }), false)
                        if !(reason.contains(f.name) && reason.contains(f.src)) =>
                    {
                        unclear.push(format!("{} ({}): {reason}", f.name, f.src))
                    }
                    _ => {}
                }
            }
        }
        // What the manual excludes first, over all fields: the substance before the wording.
        assert!(accepted.is_empty(), "accepted, not listed: {accepted:?}");
        assert!(refused.is_empty(), "refused, listed: {refused:?}");
        assert!(
            unclear.is_empty(),
            "errors without the field and the manual: {unclear:?}"
        );
    }

    /// A one-character field: every letter and digit is a candidate.
    fn field(name: &'static str, src: &'static str, listed: &[&str]) -> Field {
        field_of(name, src, listed, chars())
    }

    fn field_of(
        name: &'static str,
        src: &'static str,
        listed: &[&str],
        candidates: Vec<String>,
    ) -> Field {
        Field {
            name,
            src,
            listed: listed.iter().map(|v| v.to_string()).collect(),
            candidates,
        }
    }

    // --- TH, 000 §3.1 ------------------------------------------------------------------

    /// A valid TH code, field by field (boxes 1-2, 3, 4-8, 9-11, 12, 13, 14, 15, 16, 17-19,
    /// 20, 21, 22, 23-25).
    const TH: [&str; 14] = [
        "TH", "M", "0500M", "C01", "1", "E", "N", "N", "C", "304", "1", "1", "1", "",
    ];
    const TH_SRC: &str = "000 §3.1";

    #[test]
    fn th_every_field_accepts_what_000_3_1_lists_and_refuses_the_rest() {
        let connections = {
            let mut w = words("CMNFE0123", 3);
            w.push("X01".into());
            w
        };
        let fields = vec![
            (
                0,
                field_of("sensor model", TH_SRC, &["TH"], vec!["TH".into()]),
            ),
            // Table 1: flange types.
            (
                1,
                field("design", TH_SRC, &["F", "G", "M", "N", "S", "T", "W"]),
            ),
            (
                3,
                field_of(
                    "connection type",
                    TH_SRC,
                    &["C01", "C10", "M01", "M10", "N01", "N10", "NF1"],
                    connections,
                ),
            ),
            (4, field("operating voltage", TH_SRC, &["1"])),
            (5, field("version", TH_SRC, &["D", "E", "G", "N"])),
            (6, field("functional safety type", TH_SRC, &["N"])),
            (7, field("additional option type", TH_SRC, &["N"])),
            (8, field("output", TH_SRC, &["C"])),
            (
                9,
                field_of("protocol", TH_SRC, &["304"], words("0123456789", 3)),
            ),
            (10, field("baud rate", TH_SRC, &["1", "2", "3", "4"])),
            (11, field("resolution", TH_SRC, &["1", "2"])),
            (12, field("performance", TH_SRC, &["1"])),
            (
                13,
                field_of(
                    "magnet number",
                    TH_SRC,
                    &["", "Z02", "Z03", "Z04"],
                    [
                        "", "Z00", "Z01", "Z02", "Z03", "Z04", "Z05", "Z09", "Z12", "Y02",
                    ]
                    .map(String::from)
                    .to_vec(),
                ),
            ),
        ];
        check_fields(&TH, &fields);
    }

    #[test]
    fn th_fields_decode_as_000_3_1_says() {
        for (baud, kbit) in [("1", 1000), ("2", 500), ("3", 250), ("4", 125)] {
            let c = parse_order_code(&with(&TH, 10, baud)).unwrap();
            assert_eq!(c.bit_rate_kbit, kbit);
        }
        for (res, um) in [("1", 5), ("2", 2)] {
            assert_eq!(
                parse_order_code(&with(&TH, 11, res)).unwrap().resolution_um,
                um
            );
        }
        for (z, n) in [("", 1), ("Z02", 2), ("Z03", 3), ("Z04", 4)] {
            assert_eq!(parse_order_code(&with(&TH, 13, z)).unwrap().magnets, n);
        }
        let c = parse_order_code("TH M 0500M C01 1 D N N C304 1 1 1").unwrap();
        assert_eq!(
            (
                c.model_name(),
                c.stroke_mm,
                c.bit_rate_kbit,
                c.resolution_um
            ),
            ("th", 500.0, 1000, 5)
        );
        assert_eq!(c.normalized, "THM0500MC011DNNC304111");
        let c = parse_order_code("THT 300.0U N01 1 N N N C304 4 1 1").unwrap();
        assert_eq!(c.stroke_mm, 7620.0);
        assert_eq!(c.sensor_spec().unwrap().cycle_time_us, 4000);
    }

    /// "M01 / M10 … (Version E & N)", NF1 likewise (§4.4: "Version D & G suitable for
    /// connection types: C01, C10, N01, N10").
    #[test]
    fn th_connections_of_versions_e_and_n_only_are_refused_with_d_and_g() {
        for conn in ["C01", "C10", "M01", "M10", "N01", "N10", "NF1"] {
            for version in ["D", "E", "G", "N"] {
                let mut f = TH;
                f[3] = conn;
                f[5] = version;
                let code = f.concat();
                let all_versions = ["C01", "C10", "N01", "N10"].contains(&conn);
                if all_versions || version == "E" || version == "N" {
                    assert!(parse_order_code(&code).is_ok(), "{code}");
                } else {
                    assert_eq!(
                        reason(&code),
                        format!(
                            "connection type {conn} (box 9): only with versions E and N, not \
                             with version {version} (box 13) (000 §3.1)"
                        ),
                    );
                }
            }
        }
    }

    /// Every mm and inch code of four digits: 0025…7620 mm in 5 mm increments, 001.0…300.0
    /// in. ("Non standard stroke lengths are available; must be encoded in 5 mm / 0.1 in.
    /// increments").
    #[test]
    fn th_strokes_every_four_digit_code() {
        check_strokes(&TH, 2, TH_SRC, (25, 7620), (10, 3000));
        assert_eq!(
            reason("TH M 1503M C01 1 E N N C304 1 1 1"),
            "stroke length 1503M (box 4): non-standard strokes are encoded in 5 mm \
             increments (000 §3.1)"
        );
        assert_eq!(
            reason("THM9000MC011ENNC304111"),
            "stroke length 9000M (box 4): outside 25…7620 mm (0025M…7620M) (000 §3.1)"
        );
        assert_eq!(
            reason("THM3001UC011ENNC304111"),
            "stroke length 3001U (box 4): outside 001.0…300.0 in. (000 §3.1)"
        );
        assert!(
            reason("THM0500C011ENNC304111").starts_with("stroke length 0500C (box 4): 4 digits")
        );
    }

    fn check_strokes(
        base: &[&str],
        i: usize,
        src: &str,
        (lo, hi): (u32, u32),
        (tlo, thi): (u32, u32),
    ) {
        let (mut accepted, mut refused, mut unclear) = (vec![], vec![], vec![]);
        let mut check = |text: String, listed: bool, mm: f64, why: &str| match parse_order_code(
            &with(base, i, &text),
        ) {
            Ok(c) if listed => {
                assert!((c.stroke_mm - mm).abs() < 1e-9, "{text}: {}", c.stroke_mm)
            }
            Ok(_) => accepted.push(text),
            Err(e) if listed => refused.push(format!("{text}: {e}")),
            Err(Error::OrderCode { reason, .. }) => {
                let head = format!("stroke length {text} (box ");
                let tail = format!("({src})");
                if !(reason.starts_with(&head) && reason.contains(why) && reason.ends_with(&tail)) {
                    unclear.push(reason);
                }
            }
            Err(e) => refused.push(format!("{text}: {e}")),
        };
        for n in 0..=9999u32 {
            let in_range = (lo..=hi).contains(&n);
            let why = if in_range {
                "non-standard strokes are encoded in 5 mm increments"
            } else {
                "outside"
            };
            check(
                format!("{n:04}M"),
                in_range && n % 5 == 0,
                f64::from(n),
                why,
            );
            // The same tenths of an inch, in both forms.
            let listed = (tlo..=thi).contains(&n);
            let mm = f64::from(n) * 2.54;
            check(format!("{n:04}U"), listed, mm, "in.");
            check(format!("{:03}.{}U", n / 10, n % 10), listed, mm, "in.");
        }
        assert!(accepted.is_empty(), "accepted, excluded: {accepted:?}");
        assert!(refused.is_empty(), "refused, listed: {refused:?}");
        assert!(unclear.is_empty(), "errors without the rule: {unclear:?}");
        let c = parse_order_code(&with(base, i, "020.0U")).unwrap();
        assert_eq!(c.stroke_mm, 508.0);
    }

    // --- E-Series, 001 §3.1 (EP), §3.2 (EL), §3.3 (EH) ---------------------------------

    /// A valid E-Series code, field by field (a, b, c, d, e, f, g, h, i, j).
    fn e_series(model: &'static str) -> [&'static str; 10] {
        let design = if model == "EH" { "M" } else { "0" };
        [
            model, design, "0600M", "D34", "1", "C304", "2", "4", "1", "",
        ]
    }

    #[test]
    fn e_series_every_field_accepts_what_001_3_lists_and_refuses_the_rest() {
        for (model, src, designs, connections) in [
            ("EP", "001 §3.1", &["0"][..], &["D34"][..]),
            ("EL", "001 §3.2", &["0"][..], &["D34"][..]),
            (
                "EH",
                "001 §3.3",
                &["K", "L", "M", "S", "F", "W"][..],
                &[
                    "D34", "EH1", "EH2", "EH3", "EH4", "ET1", "ET2", "ET3", "ET4",
                ][..],
            ),
        ] {
            let base = e_series(model);
            let mut conn_candidates = words("DEHT0123456", 3);
            conn_candidates.retain(|w| !w.starts_with('0'));
            let fields = vec![
                (1, field("design", src, designs)),
                (
                    3,
                    field_of("connection type", src, connections, conn_candidates),
                ),
                (4, field("operating voltage", src, &["1"])),
                (
                    5,
                    field_of(
                        "output",
                        src,
                        &["C304", "C404"],
                        words("C0345", 4)
                            .into_iter()
                            .filter(|w| w.starts_with('C'))
                            .collect(),
                    ),
                ),
                (6, field("baud rate", src, &["1", "2", "3", "4"])),
                (7, field("resolution", src, &["4", "5"])),
                (8, field("type", src, &["1"])),
                (
                    9,
                    field_of(
                        "magnet number",
                        src,
                        &["", "Z02"],
                        ["", "Z01", "Z02", "Z03", "Z04", "Y02"]
                            .map(String::from)
                            .to_vec(),
                    ),
                ),
            ];
            check_strokes(&base, 2, src, (50, 2540), (20, 1000));
            check_fields(&base, &fields);
        }
        // The model letters themselves.
        for m in words("EPLHTX", 2) {
            let code = format!("{m}00600MD341C304241");
            let listed = ["EP", "EL", "EH"].contains(&m.as_str());
            assert_eq!(
                parse_order_code(&code).is_ok(),
                listed && m != "EH",
                "{code}"
            );
        }
        assert_eq!(
            reason("EP0 0603M D34 1 C304 2 4 1"),
            "stroke length 0603M (box 4): non-standard strokes are encoded in 5 mm \
             increments (001 §3.1)"
        );
        assert_eq!(
            reason("EL00600MEH11C304241"),
            "connection type EH1 (box 9): only D34 (001 §3.2)"
        );
    }

    #[test]
    fn e_series_fields_decode_as_001_3_says() {
        let c = parse_order_code("EP0 0600M D34 1 C304 2 4 1 Z02").unwrap();
        assert_eq!(c.model_name(), "e-series");
        assert_eq!(
            (
                c.variant,
                c.stroke_mm,
                c.bit_rate_kbit,
                c.resolution_um,
                c.magnets
            ),
            (Variant::Ep, 600.0, 500, 10, 2)
        );
        assert_eq!(c.normalized, "EP00600MD341C304241Z02");
        let c = parse_order_code("EL00500MD341C304251").unwrap();
        assert_eq!(
            (c.variant, c.resolution_um, c.magnets),
            (Variant::El, 20, 1)
        );
        let c = parse_order_code("ehm 1000m eh2 1 c404 4 5 1").unwrap();
        assert_eq!(
            (c.variant, c.stroke_mm, c.bit_rate_kbit, c.resolution_um),
            (Variant::Eh, 1000.0, 125, 20)
        );
        for (baud, kbit) in [("1", 1000), ("2", 500), ("3", 250), ("4", 125)] {
            let c = parse_order_code(&with(&e_series("EP"), 6, baud)).unwrap();
            assert_eq!(c.bit_rate_kbit, kbit);
        }
    }

    // --- TMI, 002 §8 and §2.1–2.3 --------------------------------------------------------

    const TMI: [&str; 7] = ["TMI", "0500", "101", "6", "1", "5", "252"];

    #[test]
    fn tmi_every_field_accepts_what_002_lists_and_refuses_the_rest() {
        let digits3 = {
            let mut w = words("0123456789", 3);
            w.push("1A1".into());
            w
        };
        let all3 = words("0123456789", 3);
        let all3: Vec<&str> = all3.iter().map(String::as_str).collect();
        let decided = "canpos reads 6xx as 6cs, docs/DECISIONS.md";
        let fields = vec![
            // Not decoded: every three digits.
            (
                2,
                field_of("mechanical configuration", "002 §8", &all3, digits3.clone()),
            ),
            (3, field("CANopen interface", "002 §8", &["6"])),
            (4, field("number of channels", decided, &["1", "2"])),
            (5, field("minimum position step", decided, &["1", "5"])),
            (
                6,
                field_of(
                    "electrical connection",
                    "002 §2.1–2.3",
                    &["105", "106", "252"],
                    digits3,
                ),
            ),
        ];
        check_fields(&TMI, &fields);
        // The range: four digits, 0050…4500 mm (the manual gives none: canpos).
        for n in 0..=9999u32 {
            let code = with(&TMI, 1, &format!("{n:04}"));
            if (50..=4500).contains(&n) {
                assert_eq!(parse_order_code(&code).unwrap().stroke_mm, f64::from(n));
            } else {
                let r = reason(&code);
                assert!(
                    r.starts_with(&format!("defined electrical range {n:04} (box 4)")),
                    "{r}"
                );
                assert!(r.contains("the manual gives no range"), "{r}");
            }
        }
        assert_eq!(
            reason("TMI 0500 101 615 253"),
            "electrical connection 253 (box 14): not one of 105, 106, 252 (002 §2.1–2.3)"
        );
        assert!(reason("TMI 05x0 101 615 252").starts_with("defined electrical range 05X0"));
        assert!(reason("TMI 0500 101 615 25").contains("electrical connection 25 (box 14)"));
    }

    #[test]
    fn tmi_fields_decode() {
        let c = parse_order_code("TMI 0500 101 615 252").unwrap();
        assert_eq!(c.model_name(), "tmi");
        assert_eq!(
            (c.stroke_mm, c.resolution_um, c.bit_rate_kbit, c.magnets),
            (500.0, 5, 250, 1)
        );
        let c = parse_order_code("TMI1200 000 621 105").unwrap();
        assert_eq!((c.stroke_mm, c.resolution_um, c.magnets), (1200.0, 1, 2));
        assert_eq!(c.sensor_spec().unwrap().min_magnet_distance_mm, 100.0);
        assert_eq!(parse_order_code("TMI0300000611106").unwrap().magnets, 1);
    }

    #[test]
    fn malformed_codes_give_clear_errors() {
        assert_eq!(reason(""), "the code is empty");
        assert!(reason("XY123").contains("unknown product"));
        assert!(reason("TLM 0500 101 615 105").contains("TLM"));
        assert_eq!(
            reason("THM0500MC011ENNC304511"),
            "baud rate 5 (box 20): not one of 1, 2, 3, 4 (000 §3.1)"
        );
        assert_eq!(
            reason("THM0500MC011ENNC30411"),
            "performance (box 22): the code ends here; only 1 (000 §3.1)"
        );
        assert_eq!(
            reason("EP00600MD341C304241Z02X"),
            "unexpected \"X\" from box 23 (the code ends after its last field, 001 §3.1)"
        );
        assert!(reason("EP0 0600µ").contains("unexpected character"));
    }

    #[test]
    fn display_is_normalized_code() {
        let c: OrderCode = "ep0 0600m d34 1 c304 2 4 1".parse().unwrap();
        assert_eq!(c.to_string(), "EP00600MD341C304241");
    }
}
