//! Trajectory CSV files (the contract of DESIGN.md): header `t`, then `q:<c>` for
//! every coordinate in model order, then `dq:<c>`, then `ddq:<c>`, and `Q:<c>` when
//! generalized forces are known, then any optional columns asked for (see
//! [`crate::derived`]). Numbers are written in Rust's shortest round-trip form, so
//! reading a file back gives the same bits. A writer may keep every k-th sample only
//! ([`sampled_rows`]).

use crate::error::{Error, Result};
use crate::expr::excerpt;
use crate::trajectory::Trajectory;
use std::io::Write;
use std::path::Path;

/// The column names of a trajectory with `names` coordinates.
pub fn header(names: &[String], with_forces: bool) -> Vec<String> {
    let mut h = vec!["t".to_string()];
    let prefixes: &[&str] = if with_forces {
        &["q", "dq", "ddq", "Q"]
    } else {
        &["q", "dq", "ddq"]
    };
    for p in prefixes {
        h.extend(names.iter().map(|c| format!("{p}:{c}")));
    }
    h
}

/// Writes a trajectory (and, if given, generalized forces, row-major samples × n).
/// Refuses non-finite values rather than writing them.
pub fn write_trajectory<W: Write>(
    out: W,
    trajectory: &Trajectory,
    forces: Option<&[f64]>,
) -> Result<()> {
    write_trajectory_with(
        out,
        trajectory,
        &CsvOptions {
            forces,
            ..CsvOptions::default()
        },
    )
}

/// What a trajectory CSV holds besides the trajectory, and which of its samples.
#[derive(Debug, Clone, Copy, Default)]
pub struct CsvOptions<'a> {
    /// Generalized forces, row-major samples × n: the `Q:<c>` columns.
    pub forces: Option<&'a [f64]>,
    /// Columns written after the standard ones: their names, and their values
    /// row-major samples × names (every sample of the trajectory).
    pub extra: Option<(&'a [String], &'a [f64])>,
    /// The samples written, in order; None writes them all.
    pub rows: Option<&'a [usize]>,
}

/// [`write_trajectory`] with extra columns and a choice of samples.
pub fn write_trajectory_with<W: Write>(
    out: W,
    trajectory: &Trajectory,
    options: &CsvOptions,
) -> Result<()> {
    let n = trajectory.n();
    let mut w = csv::Writer::from_writer(out);
    let io = |e: csv::Error| Error::data(e.to_string());
    let mut names = header(&trajectory.names, options.forces.is_some());
    let (extra_names, extra): (&[String], &[f64]) = options.extra.unwrap_or((&[], &[]));
    names.extend(extra_names.iter().cloned());
    w.write_record(names).map_err(io)?;
    let width = extra_names.len();
    let all: Vec<usize>;
    let rows = match options.rows {
        Some(rows) => rows,
        None => {
            all = (0..trajectory.len()).collect();
            &all
        }
    };
    // Each field is formatted into one reused buffer and written as it comes.
    let mut text = String::with_capacity(32);
    for &k in rows {
        let mut push = |v: f64, what: &str| -> Result<()> {
            if !v.is_finite() {
                return Err(Error::singular(format!(
                    "non-finite {what} at t = {} (sample {k}); nothing written past it",
                    trajectory.t[k]
                )));
            }
            text.clear();
            write_number(&mut text, v);
            w.write_field(&text).map_err(io)
        };
        push(trajectory.t[k], "time")?;
        for (what, v) in [
            ("position", &trajectory.q),
            ("velocity", &trajectory.dq),
            ("acceleration", &trajectory.ddq),
        ] {
            for &x in &v[k * n..(k + 1) * n] {
                push(x, what)?;
            }
        }
        if let Some(f) = options.forces {
            for &x in &f[k * n..(k + 1) * n] {
                push(x, "generalized force")?;
            }
        }
        for (j, &x) in extra[k * width..(k + 1) * width].iter().enumerate() {
            push(x, &extra_names[j])?;
        }
        w.write_record(None::<&[u8]>).map_err(io)?;
    }
    w.flush().map_err(|e| Error::data(e.to_string()))?;
    Ok(())
}

/// A trajectory CSV written row by row, as a run's steps become final: the same
/// bytes [`write_trajectory_with`] writes for the standard columns (no forces, no
/// extra columns), every `stride`-th sample and the last ([`sampled_rows`]).
pub struct CsvRows<W: Write> {
    w: csv::Writer<W>,
    stride: usize,
    text: String,
    /// Samples offered so far.
    samples: usize,
    /// The last sample offered when it was not written (its stride skipped it): it
    /// is written by [`CsvRows::finish`], being the last.
    pending: Option<Vec<f64>>,
    /// Rows written.
    rows: usize,
}

impl<W: Write> CsvRows<W> {
    /// Writes the header of a trajectory with coordinates `names`.
    pub fn new(out: W, names: &[String], stride: usize) -> Result<Self> {
        let mut w = csv::Writer::from_writer(out);
        w.write_record(header(names, false))
            .map_err(|e| Error::data(e.to_string()))?;
        Ok(CsvRows {
            w,
            stride: stride.max(1),
            text: String::with_capacity(32),
            samples: 0,
            pending: None,
            rows: 0,
        })
    }

    /// The next sample: written now when it is on the stride, else kept in case it
    /// is the last. Non-finite values are refused, as [`write_trajectory_with`]
    /// refuses them.
    pub fn sample(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()> {
        let k = self.samples;
        self.samples += 1;
        if k % self.stride == 0 {
            self.pending = None;
            self.write_row(k, t, q, dq, ddq)
        } else {
            let row = self.pending.get_or_insert_with(Vec::new);
            row.clear();
            row.push(t);
            row.extend_from_slice(q);
            row.extend_from_slice(dq);
            row.extend_from_slice(ddq);
            Ok(())
        }
    }

    fn write_row(&mut self, k: usize, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> Result<()> {
        let io = |e: csv::Error| Error::data(e.to_string());
        let fields = [
            ("time", std::slice::from_ref(&t)),
            ("position", q),
            ("velocity", dq),
            ("acceleration", ddq),
        ];
        for (what, values) in fields {
            for &v in values {
                if !v.is_finite() {
                    return Err(Error::singular(format!(
                        "non-finite {what} at t = {t} (sample {k}); nothing written past it"
                    )));
                }
                self.text.clear();
                write_number(&mut self.text, v);
                self.w.write_field(&self.text).map_err(io)?;
            }
        }
        self.w.write_record(None::<&[u8]>).map_err(io)?;
        self.rows += 1;
        Ok(())
    }

    /// Rows written so far (the last sample kept back not counted).
    pub fn rows(&self) -> usize {
        self.rows + usize::from(self.pending.is_some())
    }

    /// Writes the last sample if the stride skipped it, flushes, and gives the
    /// writer back.
    pub fn finish(mut self) -> Result<W> {
        if let Some(row) = self.pending.take() {
            let n = (row.len() - 1) / 3;
            let (t, rest) = (row[0], &row[1..]);
            self.write_row(
                self.samples - 1,
                t,
                &rest[..n],
                &rest[n..2 * n],
                &rest[2 * n..],
            )?;
        }
        self.w
            .into_inner()
            .map_err(|e| Error::data(e.error().to_string()))
    }
}

/// The sample stride of `--sample-dt`: `sample_dt / dt`, which must be a positive
/// integer to within 1e-9 relative. The error is the message (bad input).
pub fn sample_stride(dt: f64, sample_dt: f64) -> std::result::Result<usize, String> {
    let ratio = sample_dt / dt;
    let stride = ratio.round();
    if !(sample_dt > 0.0 && ratio.is_finite() && stride >= 1.0)
        || (ratio - stride).abs() > 1e-9 * ratio
    {
        return Err(format!(
            "--sample-dt {sample_dt} must be a positive integer multiple of the time step {dt}"
        ));
    }
    if stride > usize::MAX as f64 {
        return Err(format!("--sample-dt {sample_dt} is too large"));
    }
    Ok(stride as usize)
}

/// The samples kept out of `len` at every `stride`-th one: 0, stride, 2·stride, …,
/// and the last, so that the end state is always there.
pub fn sampled_rows(len: usize, stride: usize) -> Vec<usize> {
    let mut rows: Vec<usize> = (0..len).step_by(stride.max(1)).collect();
    if len > 0 && rows.last() != Some(&(len - 1)) {
        rows.push(len - 1);
    }
    rows
}

/// `v` to three significant digits, without trailing zeros.
pub fn three_digits(v: f64) -> String {
    let digits = (2.0 - v.abs().log10().floor()).clamp(0.0, 15.0) as usize;
    let text = format!("{v:.digits$}");
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        text
    }
}

/// Shortest round-trip text of a number: plain for moderate magnitudes, scientific
/// otherwise (Rust's plain form would spell 1e-30 with thirty zeros).
pub(crate) fn number(v: f64) -> String {
    let mut text = String::new();
    write_number(&mut text, v);
    text
}

/// [`number`] appended to `out`.
fn write_number(out: &mut String, v: f64) {
    use std::fmt::Write as _;
    let a = v.abs();
    if a == 0.0 || (1e-4..1e7).contains(&a) {
        // The same shortest round-trip digits as `{v}` (tested), written by ryu at a
        // third of the cost (writing the CSV is a visible part of a small run). ryu spells
        // this range in plain decimals too, whole numbers with a trailing ".0".
        let mut digits = ryu::Buffer::new();
        let text = digits.format_finite(v);
        out.push_str(text.strip_suffix(".0").unwrap_or(text));
    } else {
        // Writing into a String cannot fail.
        let _ = write!(out, "{v:e}");
    }
}

/// A numeric table read from a CSV file with a header row.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    pub columns: Vec<String>,
    /// Row-major rows × columns.
    pub values: Vec<f64>,
    pub rows: usize,
}

impl Table {
    /// The values of column `name`, if present.
    pub fn column(&self, name: &str) -> Option<Vec<f64>> {
        let j = self.columns.iter().position(|c| c == name)?;
        let w = self.columns.len();
        Some((0..self.rows).map(|i| self.values[i * w + j]).collect())
    }
}

/// Size limits for reading a table: a table beyond them is refused while it is
/// read, so a small compressed file cannot make the reader decompress and store
/// gigabytes before its first error.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TableLimits {
    /// Most values (rows × columns) kept.
    pub max_cells: usize,
    /// Most bytes read (after decompression), header included.
    pub max_bytes: u64,
}

impl Default for TableLimits {
    /// 10 million values (80 MB), a hundred times the largest reference; 256 MiB of
    /// text.
    fn default() -> Self {
        TableLimits {
            max_cells: 10_000_000,
            max_bytes: 256 << 20,
        }
    }
}

/// Longest column name accepted: names are quoted in messages.
const MAX_COLUMN_NAME: usize = 200;
/// Longest piece of a field quoted in a message.
const QUOTE: usize = 40;

/// Reads a numeric CSV table (gzip-compressed when the name ends in `.gz`, as the
/// committed references are); errors name the file, the line and the column.
/// The default [`TableLimits`] apply.
pub fn read_table(path: &Path) -> Result<Table> {
    read_table_with(path, &TableLimits::default(), &mut |_| Ok(()))
}

/// [`read_table`] with explicit limits and a check of the header that runs before
/// any row is read (say, that the columns are coordinates of a model), so a header
/// error surfaces at once however long the file.
pub fn read_table_with(
    path: &Path,
    limits: &TableLimits,
    check_header: &mut dyn FnMut(&[String]) -> Result<()>,
) -> Result<Table> {
    let file = path.display().to_string();
    let raw = std::fs::File::open(path).map_err(|e| Error::data_in(&file, None, e.to_string()))?;
    let input: Box<dyn std::io::Read> = if path.extension().is_some_and(|e| e == "gz") {
        Box::new(flate2::read::GzDecoder::new(raw))
    } else {
        Box::new(raw)
    };
    read_table_from(input, &file, limits, check_header)
}

/// Reads a table from uncompressed CSV text; `file` names it in messages.
pub fn read_table_from<R: std::io::Read>(
    input: R,
    file: &str,
    limits: &TableLimits,
    check_header: &mut dyn FnMut(&[String]) -> Result<()>,
) -> Result<Table> {
    read_table_impl(input, file, limits, check_header, false)
}

/// [`read_table_with`] of a table whose cells may be empty (a measurement file,
/// where an empty cell is a time without a reading): an empty cell reads as NaN.
pub fn read_table_with_gaps(
    path: &Path,
    limits: &TableLimits,
    check_header: &mut dyn FnMut(&[String]) -> Result<()>,
) -> Result<Table> {
    let file = path.display().to_string();
    let raw = std::fs::File::open(path).map_err(|e| Error::data_in(&file, None, e.to_string()))?;
    let input: Box<dyn std::io::Read> = if path.extension().is_some_and(|e| e == "gz") {
        Box::new(flate2::read::GzDecoder::new(raw))
    } else {
        Box::new(raw)
    };
    read_table_impl(input, &file, limits, check_header, true)
}

fn read_table_impl<R: std::io::Read>(
    input: R,
    file: &str,
    limits: &TableLimits,
    check_header: &mut dyn FnMut(&[String]) -> Result<()>,
    gaps: bool,
) -> Result<Table> {
    let mut r = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_reader(Bounded {
            inner: input,
            left: limits.max_bytes,
            exceeded: false,
        });
    let too_big = |file: &str| {
        Error::data_in(
            file,
            None,
            format!(
                "larger than {} bytes, the limit for a table; refused",
                limits.max_bytes
            ),
        )
    };
    let headers = r
        .headers()
        .map(|h| h.iter().map(str::to_string).collect::<Vec<_>>());
    let columns = match headers {
        Ok(columns) => columns,
        Err(_) if r.get_ref().exceeded => return Err(too_big(file)),
        Err(e) => return Err(Error::data_in(file, None, csv_error(&e))),
    };
    if columns.is_empty() || columns.iter().all(|c| c.is_empty()) {
        return Err(Error::data_in(file, None, "no header row"));
    }
    if columns[0].starts_with('#') {
        return Err(Error::data_in(
            file,
            Some(1),
            "begins with `#`, a comment: a table has none; delete the comment lines, so that \
             the header is the first line",
        ));
    }
    if columns.len() > limits.max_cells {
        return Err(Error::data_in(
            file,
            None,
            format!(
                "{} columns, more than the limit of {} values for a table",
                columns.len(),
                limits.max_cells
            ),
        ));
    }
    for c in &columns {
        if c.chars().count() > MAX_COLUMN_NAME || c.chars().any(char::is_control) {
            return Err(Error::data_in(
                file,
                Some(1),
                format!(
                    "column name `{}` is not one line of at most {MAX_COLUMN_NAME} characters",
                    excerpt(c, QUOTE)
                ),
            ));
        }
    }
    check_header(&columns)?;
    let width = columns.len();
    let max_rows = limits.max_cells / width;
    let mut values = Vec::new();
    let mut rows = 0;
    let mut record = csv::StringRecord::new();
    loop {
        let more = match r.read_record(&mut record) {
            Ok(more) => more,
            Err(_) if r.get_ref().exceeded => return Err(too_big(file)),
            Err(e) => {
                let line = e.position().map_or(rows as u64 + 2, |p| p.line());
                return Err(Error::data_in(file, Some(line), csv_error(&e)));
            }
        };
        if !more {
            break;
        }
        let line = record.position().map_or(rows as u64 + 2, |p| p.line());
        if rows == max_rows {
            return Err(Error::data_in(file, Some(line), format!("more than {max_rows} rows of {width} columns, beyond the limit of {} values for a table; refused",
                limits.max_cells
            )));
        }
        if record.len() != width {
            return Err(Error::data_in(
                file,
                Some(line),
                format!("{} fields where the header has {width}", record.len(),),
            ));
        }
        for (j, field) in record.iter().enumerate() {
            if gaps && field.is_empty() {
                values.push(f64::NAN);
                continue;
            }
            let v: f64 = field.parse().map_err(|_| {
                Error::data_in(
                    file,
                    Some(line),
                    format!(
                        "column `{}`: `{}` is not a number",
                        excerpt(&columns[j], QUOTE),
                        excerpt(field, QUOTE)
                    ),
                )
            })?;
            if !v.is_finite() {
                return Err(Error::data_in(
                    file,
                    Some(line),
                    format!(
                        "column `{}`: {} is not finite",
                        excerpt(&columns[j], QUOTE),
                        excerpt(field, QUOTE)
                    ),
                ));
            }
            values.push(v);
        }
        rows += 1;
    }
    Ok(Table {
        columns,
        values,
        rows,
    })
}

/// Reads a trajectory CSV (the columns `t`, `q:<c>`, `dq:<c>`, `ddq:<c>` of the
/// coordinates `names`, matched by name, in any order, among any others) into a
/// [`Trajectory`]. Only the groups `needed` (q, q̇, q̈) must be present; a group
/// not needed and absent is zeros. A missing column is an error naming it; the
/// times must increase.
pub fn read_trajectory(path: &Path, names: &[String], needed: [bool; 3]) -> Result<Trajectory> {
    let file = path.display().to_string();
    let table = read_table_with(path, &TableLimits::default(), &mut |columns| {
        check_trajectory_header(names, columns, &file, needed)
    })?;
    trajectory_from_table(names, &table, &file, needed)
}

const GROUPS: [&str; 3] = ["q", "dq", "ddq"];

/// That `columns` hold `t` and the groups `needed` of the coordinates `names`.
fn check_trajectory_header(
    names: &[String],
    columns: &[String],
    file: &str,
    needed: [bool; 3],
) -> Result<()> {
    let has = |c: &str| columns.iter().any(|h| h == c);
    if !has("t") {
        return Err(Error::data_in(file, Some(1), "no column `t`"));
    }
    for (p, _) in GROUPS.iter().zip(needed).filter(|(_, need)| *need) {
        if let Some(c) = names.iter().find(|c| !has(&format!("{p}:{c}"))) {
            return Err(Error::data_in(
                file,
                Some(1),
                format!(
                    "no column `{p}:{}` (a trajectory has t, q:<c>, dq:<c> and ddq:<c> for every coordinate c)",
                    excerpt(c, QUOTE)
                ),
            ));
        }
    }
    Ok(())
}

/// [`read_trajectory`] of a table already read; `file` names it in messages.
pub fn trajectory_from_table(
    names: &[String],
    table: &Table,
    file: &str,
    needed: [bool; 3],
) -> Result<Trajectory> {
    check_trajectory_header(names, &table.columns, file, needed)?;
    if table.rows == 0 {
        return Err(Error::data_in(file, None, "no rows"));
    }
    let t = table.column("t").unwrap_or_default();
    if let Some(k) = (1..t.len()).find(|&k| !(t[k] > t[k - 1])) {
        return Err(Error::data_in(
            file,
            Some(k as u64 + 2),
            format!("t = {} does not come after t = {}", t[k], t[k - 1]),
        ));
    }
    let (rows, n) = (table.rows, names.len());
    let mut groups = [
        vec![0.0; rows * n],
        vec![0.0; rows * n],
        vec![0.0; rows * n],
    ];
    for (g, p) in groups.iter_mut().zip(GROUPS) {
        for (i, c) in names.iter().enumerate() {
            if let Some(col) = table.column(&format!("{p}:{c}")) {
                for (k, v) in col.into_iter().enumerate() {
                    g[k * n + i] = v;
                }
            }
        }
    }
    let [q, dq, ddq] = groups;
    Ok(Trajectory {
        names: names.to_vec(),
        t,
        q,
        dq,
        ddq,
    })
}

/// A CSV error in one line of plain words (the csv crate's messages for bad UTF-8
/// and I/O may carry Debug text and positions already named).
fn csv_error(e: &csv::Error) -> String {
    match e.kind() {
        csv::ErrorKind::Utf8 { .. } => "invalid UTF-8".to_string(),
        csv::ErrorKind::Io(io) => format!("read error: {}", excerpt(&io.to_string(), 120)),
        _ => excerpt(&e.to_string(), 120),
    }
}

/// A reader that fails once more than `left` bytes have been read.
struct Bounded<R> {
    inner: R,
    left: u64,
    exceeded: bool,
}

impl<R: std::io::Read> std::io::Read for Bounded<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        // One byte past the limit tells a file of exactly the limit from a longer one.
        let want = buf.len().min(
            usize::try_from(self.left)
                .unwrap_or(usize::MAX)
                .saturating_add(1),
        );
        let n = self.inner.read(&mut buf[..want])?;
        if n as u64 > self.left {
            self.exceeded = true;
            return Err(std::io::Error::other("size limit exceeded"));
        }
        self.left -= n as u64;
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The text of a number is exactly Rust's own shortest form, as it was before
    /// the rows were written by ryu: over every binade of the plain range, the
    /// boundaries, whole numbers, signed zeros and a million pseudo-random values.
    #[test]
    fn numbers_are_spelled_as_rust_spells_them() {
        let reference = |v: f64| {
            let a = v.abs();
            if a == 0.0 || (1e-4..1e7).contains(&a) {
                format!("{v}")
            } else {
                format!("{v:e}")
            }
        };
        let mut cases = vec![
            0.0,
            -0.0,
            1.0,
            -1.0,
            1e-4,
            9.999_999_999_999_999e-5,
            1e7,
            9_999_999.999_999_998,
            0.1,
            0.2 + 0.1,
            1.0 / 3.0,
            1e6,
            123_456.0,
            5e-324,
            1e300,
            f64::MAX,
            -2.5e-5,
            std::f64::consts::PI,
        ];
        // A xorshift sequence over the bits: every exponent the plain range spans.
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        for _ in 0..1_000_000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            // Exponents 2^-15 .. 2^25, either sign, any mantissa.
            let exponent = 1008 + (state >> 52) % 41;
            let bits = (state & 0x800F_FFFF_FFFF_FFFF) | (exponent << 52);
            cases.push(f64::from_bits(bits));
        }
        cases.extend((0..10_000).map(|i| i as f64 * 0.001));
        cases.extend((0..10_000).map(|i| (i * 997) as f64));
        for v in cases {
            let mut text = String::new();
            write_number(&mut text, v);
            assert_eq!(text, reference(v), "bits {:#x}", v.to_bits());
        }
    }

    #[test]
    fn written_trajectory_reads_back_bit_for_bit() {
        let tr = Trajectory {
            names: vec!["P1.x".into(), "theta".into()],
            t: vec![0.0, 0.001],
            q: vec![1.0, 0.1, 0.999_999_5, std::f64::consts::PI],
            dq: vec![0.0, -1e-300, 2.5, 3.0],
            ddq: vec![1.0 / 3.0, 0.0, -9.81, 1e10],
        };
        let mut buf = Vec::new();
        write_trajectory(&mut buf, &tr, None).unwrap();
        let text = String::from_utf8(buf).unwrap();
        assert!(text.starts_with("t,q:P1.x,q:theta,dq:P1.x,dq:theta,ddq:P1.x,ddq:theta\n"));
        let dir = std::env::temp_dir().join(format!("mbfg-io-{}.csv", std::process::id()));
        std::fs::write(&dir, &text).unwrap();
        let table = read_table(&dir).unwrap();
        std::fs::remove_file(&dir).ok();
        assert_eq!(table.rows, 2);
        assert_eq!(table.column("q:theta").unwrap()[1], std::f64::consts::PI);
        assert_eq!(table.column("ddq:P1.x").unwrap()[0], 1.0 / 3.0);
        assert_eq!(table.column("dq:theta").unwrap()[0], -1e-300);
    }

    #[test]
    fn non_finite_values_are_refused() {
        let tr = Trajectory {
            names: vec!["a".into()],
            t: vec![0.0],
            q: vec![f64::NAN],
            dq: vec![0.0],
            ddq: vec![0.0],
        };
        let err = write_trajectory(Vec::new(), &tr, None).unwrap_err();
        assert!(err.to_string().contains("non-finite position"), "{err}");
    }

    #[test]
    fn extra_columns_follow_and_rows_are_chosen() {
        let tr = Trajectory {
            names: vec!["a".into()],
            t: vec![0.0, 0.5, 1.0],
            q: vec![1.0, 2.0, 3.0],
            dq: vec![0.0; 3],
            ddq: vec![0.0; 3],
        };
        let names = vec!["kinetic".to_string()];
        let values = [10.0, 20.0, 30.0];
        let mut buf = Vec::new();
        let options = CsvOptions {
            extra: Some((&names, &values)),
            rows: Some(&[0, 2]),
            ..CsvOptions::default()
        };
        write_trajectory_with(&mut buf, &tr, &options).unwrap();
        assert_eq!(
            String::from_utf8(buf).unwrap(),
            "t,q:a,dq:a,ddq:a,kinetic\n0,1,0,0,10\n1,3,0,0,30\n"
        );
        let bad = [10.0, f64::INFINITY, 30.0];
        let options = CsvOptions {
            extra: Some((&names, &bad)),
            ..CsvOptions::default()
        };
        let err = write_trajectory_with(Vec::new(), &tr, &options).unwrap_err();
        assert!(err.to_string().contains("non-finite kinetic"), "{err}");
    }

    #[test]
    fn sample_stride_is_a_whole_number_of_steps() {
        assert_eq!(sample_stride(0.001, 0.01), Ok(10));
        assert_eq!(sample_stride(0.001, 0.001), Ok(1));
        // 0.003 / 0.001 is 2.9999999999999996 in floating point.
        assert_eq!(sample_stride(0.001, 0.003), Ok(3));
        for bad in [0.0015, 0.0005, 0.0, -0.01, f64::NAN, f64::INFINITY] {
            let e = sample_stride(0.001, bad).unwrap_err();
            assert!(e.contains("integer multiple"), "{e}");
        }
        assert_eq!(sampled_rows(7, 3), [0, 3, 6]);
        assert_eq!(sampled_rows(8, 3), [0, 3, 6, 7]);
        assert_eq!(sampled_rows(1, 3), [0]);
        assert!(sampled_rows(0, 3).is_empty());
    }
}
