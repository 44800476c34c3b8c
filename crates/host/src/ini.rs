//! A small INI reader for EDS / DCF files (CiA 306), keeping the line of every section and key
//! so that a mistake in a user's file can be reported where it is.
//!
//! CiA 306 INI: `[section]` lines, `key=value` lines, comments starting with `;`. Section and
//! key names are case-insensitive. A section or a key given twice is an error (two
//! definitions of one object would otherwise silently pick one).

use std::fmt;

/// One `key=value` line.
#[derive(Clone, Debug)]
pub struct Key {
    /// The key as written.
    pub name: String,
    /// The value, trimmed.
    pub value: String,
    /// 1-based line number.
    pub line: usize,
}

/// One `[section]` with its keys in file order.
#[derive(Clone, Debug)]
pub struct Section {
    /// The name between the brackets, as written (trimmed).
    pub name: String,
    /// 1-based line number of the `[section]` line.
    pub line: usize,
    /// The keys in file order.
    pub keys: Vec<Key>,
}

impl Section {
    /// The key `name` (case-insensitive).
    pub fn key(&self, name: &str) -> Option<&Key> {
        self.keys.iter().find(|k| k.name.eq_ignore_ascii_case(name))
    }

    /// The value of key `name` (case-insensitive).
    pub fn get(&self, name: &str) -> Option<&str> {
        self.key(name).map(|k| k.value.as_str())
    }
}

/// A syntax error: the line and what is wrong with it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct IniError {
    /// 1-based line number.
    pub line: usize,
    /// What is wrong.
    pub msg: String,
}

impl fmt::Display for IniError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "line {}: {}", self.line, self.msg)
    }
}

impl std::error::Error for IniError {}

/// A parsed INI file.
#[derive(Clone, Debug, Default)]
pub struct Ini {
    /// Sections in file order.
    pub sections: Vec<Section>,
}

impl Ini {
    /// Parses INI text. Lines that are neither sections, `key=value` nor comments are errors,
    /// as are keys before the first section and repeated sections or keys.
    pub fn parse(text: &str) -> Result<Ini, IniError> {
        let mut ini = Ini::default();
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        for (n, raw) in text.lines().enumerate() {
            let line = n + 1;
            let l = raw.trim();
            if l.is_empty() || l.starts_with(';') {
                continue;
            }
            let err = |msg: String| Err(IniError { line, msg });
            if let Some(rest) = l.strip_prefix('[') {
                let Some(name) = rest.strip_suffix(']') else {
                    return err(format!("section header without `]`: {l}"));
                };
                let name = name.trim();
                if name.is_empty() {
                    return err("empty section name".into());
                }
                if let Some(first) = ini.section(name) {
                    return err(format!(
                        "section [{name}] given twice (first on line {})",
                        first.line
                    ));
                }
                ini.sections.push(Section {
                    name: name.to_string(),
                    line,
                    keys: Vec::new(),
                });
                continue;
            }
            let Some((k, v)) = l.split_once('=') else {
                return err(format!("not `key=value`: {l}"));
            };
            let k = k.trim();
            if k.is_empty() {
                return err(format!("no key before `=`: {l}"));
            }
            let Some(sec) = ini.sections.last_mut() else {
                return err(format!("key `{k}` before the first [section]"));
            };
            if let Some(first) = sec.key(k) {
                return err(format!(
                    "key `{k}` given twice in [{}] (first on line {})",
                    sec.name, first.line
                ));
            }
            sec.keys.push(Key {
                name: k.to_string(),
                value: v.trim().to_string(),
                line,
            });
        }
        Ok(ini)
    }

    /// The section `name` (case-insensitive).
    pub fn section(&self, name: &str) -> Option<&Section> {
        self.sections
            .iter()
            .find(|s| s.name.eq_ignore_ascii_case(name))
    }

    /// Value of `key` (case-insensitive) in section `name`.
    pub fn get(&self, name: &str, key: &str) -> Option<&str> {
        self.section(name)?.get(key)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sections_keys_and_lines() {
        let ini = Ini::parse("\u{feff}; c\n[A]\nx = 1\r\n\n[b]\nY=two words \n").unwrap();
        assert_eq!(ini.sections.len(), 2);
        let b = ini.section("B").unwrap();
        assert_eq!(b.line, 5);
        assert_eq!(b.key("y").unwrap().line, 6);
        assert_eq!(ini.get("a", "X"), Some("1"));
        assert_eq!(ini.get("b", "y"), Some("two words"));
        assert_eq!(ini.get("b", "x"), None);
    }

    #[test]
    fn errors_name_the_line() {
        let e = |t: &str| Ini::parse(t).unwrap_err();
        assert_eq!(e("x=1\n").line, 1);
        assert!(e("x=1\n").msg.contains("before the first"));
        assert_eq!(e("[a]\n\njunk\n").line, 3);
        assert_eq!(e("[a\n").line, 1);
        assert_eq!(e("[]\n").line, 1);
        assert_eq!(e("[a]\n=3\n").line, 2);
        let dup = e("[a]\nk=1\n[A]\n");
        assert_eq!(dup.line, 3);
        assert!(dup.msg.contains("first on line 1"), "{}", dup.msg);
        let dupk = e("[a]\nk=1\nK=2\n");
        assert_eq!(dupk.line, 3);
        assert!(dupk.msg.contains("twice"), "{}", dupk.msg);
    }
}
