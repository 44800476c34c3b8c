//! Order-code parsing for the three products.
//!
//! Whitespace is ignored and letters may be given in any case, so `"EP0 0600M D34 1 C304 2 4 1
//! Z02"` and `"ep00600md341c304241z02"` are the same code. Positions in error messages are
//! 1-based box numbers of the whitespace-free code.
//!
//! # Temposonics TH (000 §3.1)
//!
//! ```text
//! box   1-2  3  4-8    9-11  12  13  14  15  16-19  20    21   22    [23-25]
//!       T H  b  cccc M  ddd  e   f   g   h   C304   baud  res  perf  [Z0n]
//! ```
//!
//! * b design: `F G M N S T W` (Table 1 flange types);
//! * c stroke: 4 digits + `M` (mm, 0025…7620) or 4 digits / `ddd.d` + `U` (tenths of an inch,
//!   001.0…300.0 in.);
//! * d connection: `C01 C10 M01 M10 N01 N10 NF1`;
//! * e operating voltage `1` (+24 VDC); f version `D E G N`; g functional safety and
//!   h additional option: one letter or digit each (the manual lists `N`);
//! * protocol `C304` (CANopen); baud `1` 1000, `2` 500, `3` 250, `4` 125 kbit/s;
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
//! * c stroke: 4 digits + `M` (0050…2540 mm) or 4 digits / `ddd.d` + `U` (002.0…100.0 in.);
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
//! * rrrr: defined electrical range in mm (the stroke);
//! * mmm: mechanical configuration (three digits, not decoded);
//! * 6cs: CANopen interface. The manual only shows it as `6xx`; canpos decides (not in the
//!   manual): c = number of position channels (`1` or `2`), s = minimum position step
//!   (`1` = 1 µm, `5` = 5 µm), matching the product-code bits 31 / 30 of 002 §1.8;
//! * eee: electrical connection, three digits (`105` 6-pin IEC 130-9, `106` 5-pin M12,
//!   `252` cable are the manual's examples).
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

struct Cursor<'a> {
    code: &'a str,
    chars: Vec<char>,
    pos: usize,
}

impl Cursor<'_> {
    fn err(&self, reason: String) -> Error {
        Error::OrderCode {
            code: self.code.to_string(),
            reason,
        }
    }

    /// Takes one character for `what`, which must be one of `allowed` (empty: any letter or
    /// digit).
    fn one_of(&mut self, what: &str, allowed: &[char]) -> Result<char> {
        let box_no = self.pos + 1;
        let Some(&c) = self.chars.get(self.pos) else {
            return Err(self.err(format!("the code ends before box {box_no} ({what})")));
        };
        let ok = if allowed.is_empty() {
            c.is_ascii_alphanumeric()
        } else {
            allowed.contains(&c)
        };
        if !ok {
            let list: String = if allowed.is_empty() {
                "a letter or digit".into()
            } else {
                allowed
                    .iter()
                    .map(|c| c.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            return Err(self.err(format!("box {box_no} ({what}): '{c}' is not one of {list}")));
        }
        self.pos += 1;
        Ok(c)
    }

    /// Takes the literal `lit` for `what`.
    fn literal(&mut self, what: &str, lit: &str) -> Result<()> {
        let box_no = self.pos + 1;
        let got: String = self.chars.iter().skip(self.pos).take(lit.len()).collect();
        if got != lit {
            let got = if got.is_empty() {
                "the end of the code".to_string()
            } else {
                format!("\"{got}\"")
            };
            return Err(self.err(format!(
                "box {box_no} ({what}): expected \"{lit}\", found {got}"
            )));
        }
        self.pos += lit.len();
        Ok(())
    }

    /// Takes one of the multi-character `options` for `what`.
    fn word(&mut self, what: &str, options: &[&str]) -> Result<String> {
        let box_no = self.pos + 1;
        for o in options {
            let got: String = self.chars.iter().skip(self.pos).take(o.len()).collect();
            if got == *o {
                self.pos += o.len();
                return Ok(got);
            }
        }
        let got: String = self.chars.iter().skip(self.pos).take(3).collect();
        Err(self.err(format!(
            "box {box_no} ({what}): \"{got}\" is not one of {}",
            options.join(", ")
        )))
    }

    /// Takes exactly `n` digits for `what`.
    fn digits(&mut self, what: &str, n: usize) -> Result<u32> {
        let box_no = self.pos + 1;
        let got: String = self.chars.iter().skip(self.pos).take(n).collect();
        if got.len() != n || !got.chars().all(|c| c.is_ascii_digit()) {
            return Err(self.err(format!(
                "box {box_no} ({what}): expected {n} digits, found \"{got}\""
            )));
        }
        self.pos += n;
        got.parse()
            .map_err(|_| self.err(format!("box {box_no} ({what}): bad number")))
    }

    /// Parses the stroke field: `ddddM` (mm) or `ddddU` / `ddd.dU` (inches, tenths).
    fn stroke(&mut self, model: Model) -> Result<f64> {
        let start = self.pos;
        let box_no = start + 1;
        let mut text = String::new();
        while let Some(&c) = self.chars.get(self.pos) {
            if c.is_ascii_digit() || c == '.' {
                text.push(c);
                self.pos += 1;
            } else {
                break;
            }
        }
        let unit = self.chars.get(self.pos).copied();
        let (lo, hi) = model.stroke_range_mm();
        let mm = match unit {
            Some('M') if text.len() == 4 && !text.contains('.') => {
                self.pos += 1;
                text.parse::<f64>().ok()
            }
            Some('U') if text.len() == 4 && !text.contains('.') => {
                self.pos += 1;
                text.parse::<f64>().ok().map(|tenths| tenths / 10.0 * 25.4)
            }
            Some('U') if text.len() == 5 && text.find('.') == Some(3) => {
                self.pos += 1;
                text.parse::<f64>().ok().map(|inch| inch * 25.4)
            }
            _ => None,
        };
        let Some(mm) = mm else {
            return Err(self.err(format!(
                "box {box_no} (stroke length): expected 4 digits and M (mm, e.g. 0500M) or \
                 4 digits / ddd.d and U (inches, e.g. 020.0U), found \"{}\"",
                self.chars.iter().skip(start).take(6).collect::<String>()
            )));
        };
        // Inch strokes are rounded to the µm so that e.g. 020.0U gives exactly 508 mm.
        let mm = (mm * 1000.0).round() / 1000.0;
        if mm < lo || mm > hi {
            return Err(self.err(format!(
                "box {box_no} (stroke length): {mm} mm is outside {lo}…{hi} mm"
            )));
        }
        Ok(mm)
    }

    fn at_end(&self) -> bool {
        self.pos >= self.chars.len()
    }

    fn expect_end(&self) -> Result<()> {
        if self.at_end() {
            Ok(())
        } else {
            let rest: String = self.chars[self.pos..].iter().collect();
            Err(self.err(format!("unexpected \"{rest}\" from box {}", self.pos + 1)))
        }
    }
}

fn baud_digit(c: char) -> u32 {
    match c {
        '1' => 1000,
        '2' => 500,
        '3' => 250,
        _ => 125,
    }
}

fn parse_th(p: &mut Cursor<'_>) -> Result<OrderCode> {
    p.literal("sensor model", "TH")?;
    p.one_of("design / flange type", &['F', 'G', 'M', 'N', 'S', 'T', 'W'])?;
    let stroke_mm = p.stroke(Model::Th)?;
    p.word(
        "connection type",
        &["C01", "C10", "M01", "M10", "N01", "N10", "NF1"],
    )?;
    p.one_of("operating voltage", &['1'])?;
    p.one_of("version", &['D', 'E', 'G', 'N'])?;
    p.one_of("functional safety type", &[])?;
    p.one_of("additional option type", &[])?;
    p.literal("output / protocol", "C304")?;
    let baud = p.one_of("baud rate", &['1', '2', '3', '4'])?;
    let res = p.one_of("resolution", &['1', '2'])?;
    p.one_of("performance", &['1'])?;
    let magnets = if p.at_end() {
        1
    } else {
        p.literal("magnet number", "Z0")?;
        let n = p.one_of("magnet number", &['2', '3', '4'])?;
        n as usize - '0' as usize
    };
    p.expect_end()?;
    Ok(OrderCode {
        model: Model::Th,
        variant: Variant::Th,
        stroke_mm,
        resolution_um: if res == '1' { 5 } else { 2 },
        bit_rate_kbit: baud_digit(baud),
        magnets,
        normalized: String::new(),
    })
}

fn parse_e(p: &mut Cursor<'_>) -> Result<OrderCode> {
    let style = p.word("sensor model", &["EP", "EL", "EH"])?;
    let variant = match style.as_str() {
        "EP" => Variant::Ep,
        "EL" => Variant::El,
        _ => Variant::Eh,
    };
    if variant == Variant::Eh {
        p.one_of("design / flange and rod", &['K', 'L', 'M', 'S', 'F', 'W'])?;
    } else {
        p.one_of("design", &['0'])?;
    }
    let stroke_mm = p.stroke(Model::ESeries)?;
    if variant == Variant::Eh {
        p.word(
            "connection type",
            &[
                "D34", "EH1", "EH2", "EH3", "EH4", "ET1", "ET2", "ET3", "ET4",
            ],
        )?;
    } else {
        p.word("connection type", &["D34"])?;
    }
    p.one_of("operating voltage", &['1'])?;
    p.word("output", &["C304", "C404"])?;
    let baud = p.one_of("baud rate", &['1', '2', '3', '4'])?;
    let res = p.one_of("resolution", &['4', '5'])?;
    p.one_of("type", &['1'])?;
    let magnets = if p.at_end() {
        1
    } else {
        p.literal("magnet number", "Z02")?;
        2
    };
    p.expect_end()?;
    Ok(OrderCode {
        model: Model::ESeries,
        variant,
        stroke_mm,
        resolution_um: if res == '4' { 10 } else { 20 },
        bit_rate_kbit: baud_digit(baud),
        magnets,
        normalized: String::new(),
    })
}

fn parse_tmi(p: &mut Cursor<'_>) -> Result<OrderCode> {
    p.literal("type", "TMI")?;
    let box_no = p.pos + 1;
    let range = p.digits("defined electrical range in mm", 4)?;
    let (lo, hi) = Model::Tmi.stroke_range_mm();
    let stroke_mm = f64::from(range);
    if stroke_mm < lo || stroke_mm > hi {
        return Err(p.err(format!(
            "box {box_no} (defined electrical range): {range} mm is outside {lo}…{hi} mm"
        )));
    }
    p.digits("mechanical configuration", 3)?;
    p.one_of("CANopen interface", &['6'])?;
    let ch = p.one_of("CANopen interface: number of channels", &['1', '2'])?;
    let step = p.one_of(
        "CANopen interface: minimum position step (1 or 5 µm)",
        &['1', '5'],
    )?;
    p.digits("electrical connection", 3)?;
    p.expect_end()?;
    Ok(OrderCode {
        model: Model::Tmi,
        variant: Variant::Tmi,
        stroke_mm,
        resolution_um: if step == '1' { 1 } else { 5 },
        bit_rate_kbit: 250,
        magnets: if ch == '1' { 1 } else { 2 },
        normalized: String::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn e_series_example_from_the_manual_and_spec() {
        // SPEC §1: "…C304 2 5 1 Z02"; complete EP code as on MTS's E-Series nameplate.
        let c = parse_order_code("EP0 0600M D34 1 C304 2 4 1 Z02").unwrap();
        assert_eq!(c.model_name(), "e-series");
        assert_eq!(c.variant, Variant::Ep);
        assert_eq!(c.stroke_mm, 600.0);
        assert_eq!(c.bit_rate_kbit, 500);
        assert_eq!(c.resolution_um, 10);
        assert_eq!(c.magnets, 2);
        assert_eq!(c.normalized, "EP00600MD341C304241Z02");
        let c = parse_order_code("EL00500MD341C304251Z02").unwrap();
        assert_eq!(
            (c.variant, c.resolution_um, c.magnets),
            (Variant::El, 20, 2)
        );
        let c = parse_order_code("ehm 1000m eh2 1 c404 4 5 1").unwrap();
        assert_eq!(c.variant, Variant::Eh);
        assert_eq!(
            (c.stroke_mm, c.bit_rate_kbit, c.resolution_um, c.magnets),
            (1000.0, 125, 20, 1)
        );
        let c = parse_order_code("EP0 020.0U D34 1 C304 1 4 1").unwrap();
        assert_eq!(c.stroke_mm, 508.0);
        assert_eq!(c.bit_rate_kbit, 1000);
        assert_eq!(
            parse_order_code("EP00200UD341C304141").unwrap().stroke_mm,
            508.0
        );
    }

    #[test]
    fn th_codes() {
        // SPEC §1: "…C3041…" = protocol C304, baud digit 1.
        let c = parse_order_code("TH M 0500M C01 1 D N N C304 1 1 1").unwrap();
        assert_eq!(c.model_name(), "th");
        assert_eq!(
            (c.stroke_mm, c.bit_rate_kbit, c.resolution_um, c.magnets),
            (500.0, 1000, 5, 1)
        );
        let c = parse_order_code("THS7620MNF11GNNC304321Z04").unwrap();
        assert_eq!(
            (c.stroke_mm, c.bit_rate_kbit, c.resolution_um, c.magnets),
            (7620.0, 250, 2, 4)
        );
        let c = parse_order_code("THW 0025M M10 1 E N N C304 2 2 1 Z03").unwrap();
        assert_eq!((c.stroke_mm, c.magnets, c.bit_rate_kbit), (25.0, 3, 500));
        let c = parse_order_code("THT 300.0U N01 1 N N N C304 4 1 1").unwrap();
        assert_eq!(c.stroke_mm, 7620.0);
        assert_eq!(c.sensor_spec().unwrap().cycle_time_us, 4000);
    }

    #[test]
    fn tmi_codes() {
        let c = parse_order_code("TMI 0500 101 615 252").unwrap();
        assert_eq!(c.model_name(), "tmi");
        assert_eq!(
            (c.stroke_mm, c.resolution_um, c.bit_rate_kbit, c.magnets),
            (500.0, 5, 250, 1)
        );
        let c = parse_order_code("TMI1200 000 621 105").unwrap();
        assert_eq!((c.stroke_mm, c.resolution_um, c.magnets), (1200.0, 1, 2));
        assert_eq!(c.sensor_spec().unwrap().min_magnet_distance_mm, 100.0);
    }

    fn reason(code: &str) -> String {
        match parse_order_code(code) {
            Err(Error::OrderCode { reason, .. }) => reason,
            other => panic!("expected an order-code error for {code:?}, got {other:?}"),
        }
    }

    #[test]
    fn malformed_codes_give_clear_errors() {
        assert_eq!(reason(""), "the code is empty");
        assert!(reason("XY123").contains("unknown product"));
        assert!(reason("TLM 0500 101 615 105").contains("TLM"));
        assert!(reason("THM0500MC011DNNC304511").contains("box 20 (baud rate): '5'"));
        assert!(reason("THM0500MC011DNNC304131").contains("box 21 (resolution)"));
        assert!(reason("THM0500MC011DNNC305111").contains("expected \"C304\""));
        assert!(reason("THM9000MC011DNNC304111").contains("outside 25…7620 mm"));
        assert!(reason("THM0500C011DNNC304111").contains("stroke length"));
        assert!(reason("THM0500MC011DNNC304111Z05").contains("magnet number"));
        assert!(reason("THM0500MC011DNNC30411").contains("ends before box 22"));
        assert!(reason("THM0500MC011DNNC304111X").contains("magnet number"));
        assert!(reason("EP00600MD341C304241Z03").contains("expected \"Z02\""));
        assert!(reason("EP00600MD341C304241Z02X").contains("unexpected \"X\""));
        assert!(reason("EP00600MD341C304261").contains("box 18 (resolution)"));
        assert!(reason("EP02600MD341C304241").contains("outside 50…2540 mm"));
        assert!(reason("EPK0600MD341C304241").contains("box 3 (design)"));
        assert!(reason("EH00600MD341C304241").contains("box 3 (design / flange and rod)"));
        assert!(reason("EP00600MEH11C304241").contains("connection type"));
        assert!(reason("TMI 0500 101 635 252").contains("number of channels"));
        assert!(reason("TMI 0500 101 612 252").contains("minimum position step"));
        assert!(reason("TMI 0500 101 515 252").contains("CANopen interface"));
        assert!(reason("TMI 05x0 101 615 252").contains("defined electrical range"));
        assert!(reason("TMI 0010 101 615 252").contains("outside 50…4500 mm"));
        assert!(reason("TMI 0500 101 615 25").contains("electrical connection"));
        assert!(reason("EP0 0600µ").contains("unexpected character"));
    }

    #[test]
    fn display_is_normalized_code() {
        let c: OrderCode = "ep0 0600m d34 1 c304 2 4 1".parse().unwrap();
        assert_eq!(c.to_string(), "EP00600MD341C304241");
    }
}
