//! The FMU's resource file (`resources/canpos-fmu.txt`): `key = value` lines that say what
//! the FMU is. A leaf: the kinds read it, and it knows none of them.

/// The file under `resources/` that names the kind.
pub const RESOURCE_FILE: &str = "canpos-fmu.txt";
/// Largest resource file read (a real one has a few lines).
const MAX_RESOURCE_LEN: usize = 64 * 1024;
/// The `key = value` pairs of a resource file, in order.
#[derive(Debug, Clone, Default)]
pub struct Entries(pub Vec<(String, String)>);

impl Entries {
    /// Parses the resource text; line numbers in errors are 1-based.
    pub fn parse(text: &str) -> Result<Entries, String> {
        if text.len() > MAX_RESOURCE_LEN {
            return Err(format!(
                "{RESOURCE_FILE} is {} bytes, more than {MAX_RESOURCE_LEN}",
                text.len()
            ));
        }
        let mut out = Vec::new();
        for (n, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let Some((k, v)) = line.split_once('=') else {
                return Err(format!(
                    "{RESOURCE_FILE}:{}: expected `key = value`, got `{line}`",
                    n + 1
                ));
            };
            let k = k.trim().to_string();
            if out.iter().any(|(have, _): &(String, String)| *have == k) {
                return Err(format!("{RESOURCE_FILE}:{}: `{k}` given twice", n + 1));
            }
            out.push((k, v.trim().to_string()));
        }
        Ok(Entries(out))
    }

    /// The value of `key`.
    pub fn get(&self, key: &str) -> Option<&str> {
        self.0
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }

    /// Refuses keys other than `known`.
    pub fn only(&self, known: &[&str]) -> Result<(), String> {
        match self.0.iter().find(|(k, _)| !known.contains(&k.as_str())) {
            Some((k, _)) => Err(format!(
                "{RESOURCE_FILE}: unknown key `{k}` (known: {})",
                known.join(", ")
            )),
            None => Ok(()),
        }
    }
}
