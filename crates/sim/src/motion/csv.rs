//! CSV trajectories: `time_s, pos_mm (magnet 1), pos_mm (magnet 2), …`.

use std::path::Path;

use super::source::{in_range, Motion, MAX_MAGNITUDE};
use crate::error::{Error, Result};

/// Largest trajectory file read (256 MiB: hours of a kilohertz recording).
pub const MAX_FILE_BYTES: u64 = 256 << 20;

/// A recorded trajectory for one or more magnets.
///
/// Format:
///
/// * one row per time point: `time_s,pos1_mm[,pos2_mm…]`, fields separated by commas,
///   surrounding spaces ignored;
/// * blank lines and lines starting with `#` are ignored;
/// * the first non-comment line may be a header (it is one when its first field is not a
///   number), e.g. `time_s,magnet1_mm,magnet2_mm`;
/// * every row has the same number of fields (at least two); an empty position field means
///   "no magnet on the rod" at that time;
/// * times are finite and strictly increasing.
///
/// Between two rows positions are interpolated linearly; when either of the two is empty the
/// earlier value is held. Before the first row the first row applies, after the last row the
/// last row.
#[derive(Clone, Debug, PartialEq)]
pub struct CsvTrajectory {
    times: Vec<f64>,
    /// `rows[i][m]`: position of magnet m at `times[i]`.
    rows: Vec<Vec<Option<f64>>>,
    magnets: usize,
}

impl CsvTrajectory {
    /// Reads and parses a CSV file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let io = |message: String| Error::Io {
            path: path.to_path_buf(),
            message,
        };
        // Only a regular file of sane size: a FIFO or /dev/zero would block or never end.
        let meta = std::fs::metadata(path).map_err(|e| io(e.to_string()))?;
        if !meta.is_file() {
            return Err(io("not a regular file".into()));
        }
        if meta.len() > MAX_FILE_BYTES {
            return Err(io(format!(
                "{} bytes; a trajectory file may have at most {MAX_FILE_BYTES}",
                meta.len()
            )));
        }
        let text = std::fs::read_to_string(path).map_err(|e| io(e.to_string()))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses CSV text; `source_name` labels error messages (e.g. the file name).
    pub fn parse(text: &str, source_name: &str) -> Result<Self> {
        let err = |line: usize, reason: String| Error::Csv {
            source_name: source_name.to_string(),
            line,
            reason,
        };
        let mut times: Vec<f64> = Vec::new();
        let mut rows = Vec::new();
        let mut width: Option<usize> = None;
        let mut seen_data_or_header = false;
        for (idx, raw) in text.lines().enumerate() {
            let line_no = idx + 1;
            let line = raw.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let fields: Vec<&str> = line.split(',').map(str::trim).collect();
            if !seen_data_or_header {
                seen_data_or_header = true;
                if fields[0].parse::<f64>().is_err() {
                    // header
                    if fields.len() < 2 {
                        return Err(err(
                            line_no,
                            "the header needs a time column and at least one position column"
                                .into(),
                        ));
                    }
                    width = Some(fields.len());
                    continue;
                }
            }
            let w = *width.get_or_insert(fields.len());
            if fields.len() < 2 {
                return Err(err(
                    line_no,
                    "expected time_s and at least one position (e.g. \"0.5,120.0\")".into(),
                ));
            }
            if fields.len() != w {
                return Err(err(
                    line_no,
                    format!("expected {w} fields, found {}", fields.len()),
                ));
            }
            let t: f64 = fields[0]
                .parse()
                .map_err(|_| err(line_no, format!("time \"{}\" is not a number", fields[0])))?;
            if !in_range(t) {
                return Err(err(
                    line_no,
                    format!(
                        "time \"{}\" is not finite or beyond ±{MAX_MAGNITUDE:e} s",
                        fields[0]
                    ),
                ));
            }
            if let Some(&prev) = times.last() {
                if t <= prev {
                    return Err(err(
                        line_no,
                        format!("time {t} s does not increase (previous row: {prev} s)"),
                    ));
                }
            }
            let mut row = Vec::with_capacity(w - 1);
            for (col, f) in fields[1..].iter().enumerate() {
                if f.is_empty() {
                    row.push(None);
                    continue;
                }
                let v: f64 = f.parse().map_err(|_| {
                    err(
                        line_no,
                        format!("position {} \"{f}\" is not a number", col + 1),
                    )
                })?;
                if !in_range(v) {
                    return Err(err(
                        line_no,
                        format!(
                            "position {} \"{f}\" is not finite or beyond ±{MAX_MAGNITUDE:e} mm",
                            col + 1
                        ),
                    ));
                }
                row.push(Some(v));
            }
            times.push(t);
            rows.push(row);
        }
        if times.is_empty() {
            return Err(err(0, "no data rows".into()));
        }
        let magnets = width.unwrap_or(2) - 1;
        Ok(CsvTrajectory {
            times,
            rows,
            magnets,
        })
    }

    /// Number of position columns.
    pub fn magnet_count(&self) -> usize {
        self.magnets
    }

    /// Time of the first and of the last row, s.
    pub fn time_span_s(&self) -> (f64, f64) {
        (self.times[0], self.times[self.times.len() - 1])
    }

    /// Position of `magnet` at `t_s` (interpolated), mm.
    pub fn at(&self, magnet: usize, t_s: f64) -> Option<f64> {
        if magnet >= self.magnets {
            return None;
        }
        let i = self.times.partition_point(|&t| t <= t_s);
        if i == 0 {
            return self.rows[0][magnet];
        }
        if i == self.times.len() {
            return self.rows[i - 1][magnet];
        }
        let (t0, t1) = (self.times[i - 1], self.times[i]);
        match (self.rows[i - 1][magnet], self.rows[i][magnet]) {
            (Some(a), Some(b)) => Some(a + (b - a) * (t_s - t0) / (t1 - t0)),
            (a, _) => a,
        }
    }
}

impl Motion for CsvTrajectory {
    fn position_mm(&mut self, magnet: usize, t_s: f64) -> Option<f64> {
        self.at(magnet, t_s)
    }

    fn magnets(&self) -> usize {
        self.magnets
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err_of(text: &str) -> (usize, String) {
        match CsvTrajectory::parse(text, "traj.csv") {
            Err(Error::Csv {
                line,
                reason,
                source_name,
            }) => {
                assert_eq!(source_name, "traj.csv");
                (line, reason)
            }
            other => panic!("expected a CSV error, got {other:?}"),
        }
    }

    #[test]
    fn interpolates_and_holds() {
        let c = CsvTrajectory::parse(
            "# recorded\ntime_s,m1,m2\n0,100,500\n1,200,\n2,300,700\n",
            "x",
        )
        .unwrap();
        assert_eq!(c.magnet_count(), 2);
        assert_eq!(c.at(0, -5.0), Some(100.0));
        assert_eq!(c.at(0, 0.5), Some(150.0));
        assert_eq!(c.at(0, 1.25), Some(225.0));
        assert_eq!(c.at(0, 9.0), Some(300.0));
        assert_eq!(c.at(1, 0.5), Some(500.0)); // next is empty: hold
        assert_eq!(c.at(1, 1.5), None); // empty row held
        assert_eq!(c.at(1, 2.0), Some(700.0));
        assert_eq!(c.at(2, 1.0), None);
        assert_eq!(c.time_span_s(), (0.0, 2.0));
    }

    #[test]
    fn no_header() {
        let c = CsvTrajectory::parse("0, 10\n 2 , 30 \n", "x").unwrap();
        assert_eq!(c.at(0, 1.0), Some(20.0));
        assert_eq!(c.magnet_count(), 1);
    }

    #[test]
    fn errors_name_the_line() {
        assert_eq!(err_of(""), (0, "no data rows".into()));
        assert_eq!(err_of("# only\ntime,pos\n"), (0, "no data rows".into()));
        let (l, r) = err_of("time,pos\n0,1\n1,abc\n");
        assert_eq!(l, 3);
        assert!(r.contains("position 1 \"abc\" is not a number"), "{r}");
        let (l, r) = err_of("0,1\n\n1,2,3\n");
        assert_eq!(l, 3);
        assert!(r.contains("expected 2 fields, found 3"), "{r}");
        let (l, r) = err_of("0,1\n2,1\n1,1\n");
        assert_eq!(l, 3);
        assert!(r.contains("does not increase"), "{r}");
        let (l, r) = err_of("0,1\nx1,1\n");
        assert_eq!(l, 2);
        assert!(r.contains("time \"x1\" is not a number"), "{r}");
        let (l, _) = err_of("0,1\ninf,1\n");
        assert_eq!(l, 2);
        let (l, _) = err_of("0,NaN\n");
        assert_eq!(l, 1);
        let (l, r) = err_of("time\n");
        assert_eq!(l, 1);
        assert!(r.contains("header"));
        let (l, _) = err_of("0\n");
        assert_eq!(l, 1);
    }

    #[test]
    fn missing_file_is_an_io_error() {
        let e = CsvTrajectory::load("/nonexistent/canpos/traj.csv").unwrap_err();
        assert!(matches!(e, Error::Io { .. }));
        assert!(e.to_string().contains("/nonexistent/canpos/traj.csv"));
    }

    #[test]
    fn devices_are_refused_not_read() {
        // /dev/zero never ends; a character device is no trajectory file.
        let e = CsvTrajectory::load("/dev/zero").unwrap_err();
        assert!(e.to_string().contains("not a regular file"), "{e}");
    }
}
