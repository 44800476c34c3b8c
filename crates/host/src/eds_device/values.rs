//! The values of an EDS / DCF file: numbers (CiA 306 notation, `$NODEID+…`), data type codes,
//! access types, section names of objects. Plain parsing, below the device builder.

use canpos_stack::od::{Access, DataType};

/// An EDS number: decimal, `0x` hex, octal with a leading 0 (CiA 306), or negative decimal.
pub fn parse_int(s: &str) -> Option<i64> {
    let s = s.trim();
    let (neg, body) = match s.strip_prefix('-') {
        Some(b) => (true, b.trim_start()),
        None => (false, s),
    };
    let v = if let Some(h) = body.strip_prefix("0x").or_else(|| body.strip_prefix("0X")) {
        i64::from_str_radix(h, 16).ok()?
    } else if body.len() > 1 && body.starts_with('0') {
        i64::from_str_radix(&body[1..], 8).ok()?
    } else if body.bytes().all(|b| b.is_ascii_digit()) && !body.is_empty() {
        body.parse().ok()?
    } else {
        return None;
    };
    Some(if neg { -v } else { v })
}

/// A number that may be relative to the node-id: `$NODEID`, `$NODEID+0x180`, `0x180+$NODEID`.
/// Returns the number and whether `$NODEID` was in it (then the number is the offset).
pub fn parse_value(s: &str) -> Option<(i64, bool)> {
    let s = s.trim();
    let up = s.to_ascii_uppercase();
    let Some(at) = up.find("$NODEID") else {
        return parse_int(s).map(|v| (v, false));
    };
    let before = s[..at].trim();
    let after = s[at + "$NODEID".len()..].trim();
    let offset = match (before, after) {
        ("", "") => 0,
        ("", a) => parse_int(a.strip_prefix('+')?)?,
        (b, "") => parse_int(b.strip_suffix('+')?)?,
        _ => return None,
    };
    Some((offset, true))
}

/// [`parse_value`] with `$NODEID` resolved for `node_id` (the conformance tool's reading).
pub fn parse_number(s: &str, node_id: u8) -> Option<i64> {
    let (v, rel) = parse_value(s)?;
    Some(if rel {
        v.saturating_add(i64::from(node_id))
    } else {
        v
    })
}

pub(super) fn data_type(code: i64) -> Result<DataType, String> {
    Ok(match code {
        0x0001 => DataType::Boolean,
        0x0002 => DataType::Integer8,
        0x0003 => DataType::Integer16,
        0x0004 => DataType::Integer32,
        0x0005 => DataType::Unsigned8,
        0x0006 => DataType::Unsigned16,
        0x0007 => DataType::Unsigned32,
        0x0009 => DataType::VisibleString,
        0x000F => return Err("DOMAIN objects are not supported by canpos-stack".into()),
        0x0008 | 0x000A | 0x000B | 0x000C | 0x000D | 0x0010..=0x001B => {
            return Err(format!(
                "DataType 0x{code:04X} is not supported by canpos-stack (BOOLEAN, INTEGER8/16/32, \
                 UNSIGNED8/16/32 and VISIBLE_STRING are)"
            ))
        }
        _ => return Err(format!("unknown DataType 0x{code:04X}")),
    })
}

pub(super) fn access(s: &str) -> Option<Access> {
    Some(match s.to_ascii_lowercase().as_str() {
        "ro" => Access::Ro,
        "wo" => Access::Wo,
        "rw" | "rwr" | "rww" => Access::Rw,
        "const" => Access::Const,
        _ => return None,
    })
}

/// The raw bits of `v` as a value of `ty`. A hex number too large for a signed type is read
/// as its two's-complement bit pattern (how tools write negative limits in hex).
pub(super) fn raw_of(ty: DataType, v: i64, text: &str) -> Option<u32> {
    let (lo, hi) = ty.natural_range();
    let bits = ty.bits() as u32;
    let hex = text.trim().to_ascii_lowercase().starts_with("0x");
    let v = if ty.is_signed() && hex && v > hi && v < 1i64 << bits {
        v - (1i64 << bits)
    } else {
        v
    };
    if v < lo || v > hi {
        return None;
    }
    Some(if bits >= 32 {
        v as u32
    } else {
        (v as u32) & ((1u32 << bits) - 1)
    })
}

/// A section name that is an object (`1018` → `(0x1018, None)`) or a sub-index (`1018sub4`
/// → `(0x1018, Some(4))`), case-insensitive; `None` for every other section.
pub fn section_object(name: &str) -> Option<(u16, Option<u8>)> {
    let idx = name.get(..4)?;
    if !idx.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    let index = u16::from_str_radix(idx, 16).ok()?;
    let rest = &name[4..];
    if rest.is_empty() {
        return Some((index, None));
    }
    let sub = rest
        .get(..3)
        .filter(|p| p.eq_ignore_ascii_case("sub"))
        .map(|_| &rest[3..])?;
    if sub.is_empty() || sub.len() > 2 || !sub.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    Some((index, Some(u8::from_str_radix(sub, 16).ok()?)))
}
