//! Where a command's CSV goes, all or marked, never silently partial:
//! - to a file: written to a temporary file beside it and renamed over it only when
//!   the run succeeded, so a failure, a kill or a full disk leaves the old file as it
//!   was; the steps of a run that ended early go to `<out>.partial.csv` instead; a
//!   name ending in `.gz` is written gzip-compressed (its partial file too);
//! - to standard output or a special file (a FIFO, a device): opened once, the rows
//!   written once, and after those of a run that ended early a last line
//!   `# incomplete: …` that no CSV reader takes for a row of numbers; a signal that
//!   arrives while the writer waits on a reader ends the process at once;
//! - a consumer that stopped reading standard output (`mbfg … | head`) ends the
//!   writing quietly: the rows it wanted went out.
//!
//! Temporary files that a killed run left beside a target are removed by the next
//! run that writes it.

//! - streamed ([`Output::stream`]): the rows go to the temporary file as the run's
//!   steps become final, so that a long run holds none of them; a run made again
//!   (at a finer step) starts the file over.

use mbfg::io::{CsvOptions, CsvRows};
use mbfg::trajectory::Trajectory;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

pub struct Output {
    /// The file asked for, or None for standard output.
    target: Option<PathBuf>,
    /// The temporary file beside it, created when the output is opened (so that an
    /// unwritable directory is refused before the run) and removed unless renamed.
    temp: Option<PathBuf>,
    /// A special file (FIFO, device), opened once when the output is opened.
    special: Option<File>,
}

impl Output {
    /// Opens the output; refuses a target that is one of the command's `inputs` or
    /// whose directory cannot be written. The error is the message (bad input).
    pub fn open(out: Option<&Path>, inputs: &[&Path]) -> Result<Self, String> {
        let Some(target) = out else {
            return Ok(Output {
                target: None,
                temp: None,
                special: None,
            });
        };
        for input in inputs {
            if same_file(target, input) {
                return Err(format!(
                    "--out {} is the input {}: refusing to overwrite it",
                    target.display(),
                    input.display()
                ));
            }
        }
        if target.is_dir() {
            return Err(format!(
                "cannot write {}: it is a directory",
                target.display()
            ));
        }
        if target.exists() && !target.is_file() {
            // A device or a pipe (/dev/stdout, a FIFO): opened once (a FIFO's reader
            // sees one stream), written directly, never replaced by a rename.
            let file = super::interrupt::while_blocked(|| File::options().write(true).open(target))
                .map_err(|e| format!("cannot write {}: {e}", target.display()))?;
            return Ok(Output {
                target: Some(target.to_path_buf()),
                temp: None,
                special: Some(file),
            });
        }
        remove_stale_temps(target);
        let temp = temp_beside(target);
        File::options()
            .write(true)
            .create_new(true)
            .open(&temp)
            .map_err(|e| format!("cannot write {}: {e}", target.display()))?;
        Ok(Output {
            target: Some(target.to_path_buf()),
            temp: Some(temp),
            special: None,
        })
    }

    /// Whether the CSV goes to a file (the summary then goes to standard output).
    pub fn to_file(&self) -> bool {
        self.target.is_some()
    }

    /// Writes the complete result: to the temporary file, then renamed over the
    /// target in one step.
    pub fn commit(self, trajectory: &Trajectory, csv: &CsvOptions) -> Result<(), String> {
        self.commit_with(&|w| mbfg::io::write_trajectory_with(w, trajectory, csv))
    }

    /// [`Output::commit`] of any CSV: `body` writes it (into the temporary file, a
    /// device or standard output).
    pub fn commit_with(
        mut self,
        body: &dyn Fn(&mut dyn Write) -> mbfg::Result<()>,
    ) -> Result<(), String> {
        match (self.target.clone(), self.temp.take()) {
            (Some(target), Some(temp)) => {
                let written = write_file(&temp, is_gzip(&target), body)
                    .and_then(|()| std::fs::rename(&temp, &target).map_err(|e| e.to_string()));
                if let Err(e) = written {
                    std::fs::remove_file(&temp).ok();
                    return Err(format!("cannot write {}: {e}", target.display()));
                }
                // A partial file of an earlier failed run is stale now.
                std::fs::remove_file(partial_path(&target)).ok();
                Ok(())
            }
            (Some(target), None) => {
                let file = self.special.take().expect("a special file is opened once");
                let w = std::io::BufWriter::new(file);
                super::interrupt::while_blocked(|| encode(w, is_gzip(&target), body))
                    .map(drop)
                    .map_err(|e| format!("cannot write {}: {e}", target.display()))
            }
            _ => {
                let mut out = std::io::stdout().lock();
                match body(&mut out)
                    .and_then(|()| out.flush().map_err(|e| mbfg::Error::data(e.to_string())))
                {
                    Ok(()) => Ok(()),
                    Err(e) if super::consumer_gone(&e.to_string()) => Ok(()),
                    Err(e) => {
                        // Rows may have gone out before the error: mark them.
                        writeln!(out, "# incomplete: {}", one_line(&e.to_string())).ok();
                        Err(format!("cannot write the CSV to standard output: {e}"))
                    }
                }
            }
        }
    }

    /// Keeps the steps of a run that ended early, marked as such; the target file is
    /// left as it was. Returns where they went, for the error line.
    pub fn keep_partial(
        mut self,
        trajectory: &Trajectory,
        csv: &CsvOptions,
        why: &str,
    ) -> Result<String, String> {
        let steps = csv.rows.map_or(trajectory.len(), <[usize]>::len);
        match (self.target.clone(), self.temp.take()) {
            (Some(target), Some(temp)) => {
                let partial = partial_path(&target);
                let body = |w: &mut dyn Write| mbfg::io::write_trajectory_with(w, trajectory, csv);
                let written = write_file(&temp, is_gzip(&target), &body)
                    .and_then(|()| std::fs::rename(&temp, &partial).map_err(|e| e.to_string()));
                if let Err(e) = written {
                    std::fs::remove_file(&temp).ok();
                    return Err(format!("cannot write {}: {e}", partial.display()));
                }
                Ok(format!("{steps} steps kept in {}", partial.display()))
            }
            _ => {
                let body = |w: &mut dyn Write| mbfg::io::write_trajectory_with(w, trajectory, csv);
                self.keep_partial_with(&body, steps, why)
            }
        }
    }

    /// [`Output::keep_partial`] of any CSV: `body` writes the `steps` rows kept.
    pub fn keep_partial_with(
        mut self,
        body: &dyn Fn(&mut dyn Write) -> mbfg::Result<()>,
        steps: usize,
        why: &str,
    ) -> Result<String, String> {
        match (self.target.clone(), self.temp.take()) {
            (Some(target), Some(temp)) => {
                let partial = partial_path(&target);
                let written = write_file(&temp, is_gzip(&target), body)
                    .and_then(|()| std::fs::rename(&temp, &partial).map_err(|e| e.to_string()));
                if let Err(e) = written {
                    std::fs::remove_file(&temp).ok();
                    return Err(format!("cannot write {}: {e}", partial.display()));
                }
                Ok(format!("{steps} steps kept in {}", partial.display()))
            }
            (Some(target), None) => {
                let file = self.special.take().expect("a special file is opened once");
                let mut w = std::io::BufWriter::new(file);
                super::interrupt::while_blocked(|| marked(&mut w, body, why))
                    .map_err(|e| format!("cannot write {}: {e}", target.display()))?;
                Ok(format!(
                    "{steps} steps written to {}, then `# incomplete`",
                    target.display()
                ))
            }
            _ => {
                let mut out = std::io::stdout().lock();
                match marked(&mut out, body, why) {
                    Ok(()) => {}
                    Err(e) if super::consumer_gone(&e) => {}
                    Err(e) => return Err(format!("cannot write the CSV to standard output: {e}")),
                }
                Ok(format!("{steps} steps written, then `# incomplete`"))
            }
        }
    }

    /// A writer of the rows into the temporary file as they come (the standard
    /// columns, every `stride`-th row and the last), or None where the output is
    /// not a file written under a temporary name (standard output, a device).
    pub fn stream(&self, names: &[String], stride: usize) -> Result<Option<Streamed>, String> {
        let (Some(target), Some(temp)) = (&self.target, &self.temp) else {
            return Ok(None);
        };
        let mut streamed = Streamed {
            target: target.clone(),
            temp: temp.clone(),
            gzip: is_gzip(target),
            names: names.to_vec(),
            stride,
            rows: None,
        };
        streamed.open().map_err(|e| e.to_string())?;
        Ok(Some(streamed))
    }

    /// [`Output::commit`] of a streamed CSV: finished, then renamed over the target.
    pub fn commit_streamed(mut self, streamed: Streamed) -> Result<(), String> {
        let target = streamed.target.clone();
        let temp = self
            .temp
            .take()
            .expect("a streamed output has a temporary file");
        let written = streamed
            .finish()
            .and_then(|_| std::fs::rename(&temp, &target).map_err(|e| e.to_string()));
        if let Err(e) = written {
            std::fs::remove_file(&temp).ok();
            return Err(format!("cannot write {}: {e}", target.display()));
        }
        std::fs::remove_file(partial_path(&target)).ok();
        Ok(())
    }

    /// [`Output::keep_partial`] of a streamed CSV: the rows written so far, finished
    /// and renamed to the partial file. Returns where they went.
    pub fn keep_partial_streamed(mut self, streamed: Streamed) -> Result<String, String> {
        let partial = partial_path(&streamed.target);
        let temp = self
            .temp
            .take()
            .expect("a streamed output has a temporary file");
        let written = streamed.finish().and_then(|rows| {
            std::fs::rename(&temp, &partial)
                .map(|()| rows)
                .map_err(|e| e.to_string())
        });
        match written {
            Ok(rows) => Ok(format!("{rows} steps kept in {}", partial.display())),
            Err(e) => {
                std::fs::remove_file(&temp).ok();
                Err(format!("cannot write {}: {e}", partial.display()))
            }
        }
    }

    /// Leaves nothing behind (the target keeps its old contents).
    pub fn discard(mut self) {
        if let Some(temp) = self.temp.take() {
            std::fs::remove_file(temp).ok();
        }
    }
}

impl Drop for Output {
    fn drop(&mut self) {
        if let Some(temp) = self.temp.take() {
            std::fs::remove_file(temp).ok();
        }
    }
}

/// A CSV being written to an output's temporary file as the run's steps become
/// final ([`Output::stream`]).
pub struct Streamed {
    target: PathBuf,
    temp: PathBuf,
    gzip: bool,
    names: Vec<String>,
    stride: usize,
    rows: Option<CsvRows<Encoded>>,
}

/// The temporary file, through a gzip encoder where the target's name asks.
enum Encoded {
    Plain(std::io::BufWriter<File>),
    Gzip(flate2::write::GzEncoder<std::io::BufWriter<File>>),
}

impl Write for Encoded {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match self {
            Encoded::Plain(w) => w.write(buf),
            Encoded::Gzip(w) => w.write(buf),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match self {
            Encoded::Plain(w) => w.flush(),
            Encoded::Gzip(w) => w.flush(),
        }
    }
}

impl Streamed {
    /// (Re)starts the file: emptied, then the header.
    fn open(&mut self) -> mbfg::Result<()> {
        self.rows = None;
        let file = File::options()
            .write(true)
            .truncate(true)
            .open(&self.temp)
            .map_err(|e| self.error(e))?;
        let w = std::io::BufWriter::new(file);
        let w = if self.gzip {
            Encoded::Gzip(flate2::write::GzEncoder::new(
                w,
                flate2::Compression::default(),
            ))
        } else {
            Encoded::Plain(w)
        };
        self.rows = Some(CsvRows::new(w, &self.names, self.stride).map_err(|e| self.error(e))?);
        Ok(())
    }

    fn error(&self, e: impl std::fmt::Display) -> mbfg::Error {
        mbfg::Error::data(format!("cannot write {}: {e}", self.target.display()))
    }

    /// Writes the last row if the stride skipped it, finishes the gzip stream and
    /// puts the file on disk (before a rename, so that a crash cannot leave a renamed
    /// empty file). Returns the rows written.
    fn finish(mut self) -> Result<usize, String> {
        let rows = self.rows.take().expect("an open stream");
        let count = rows.rows();
        let mut w = rows.finish().map_err(|e| e.to_string())?;
        // Flushed once more, as the held writer's CSV writer flushes when dropped:
        // a gzip stream then ends with the same bytes.
        w.flush().map_err(|e| e.to_string())?;
        let mut w = match w {
            Encoded::Plain(w) => w,
            Encoded::Gzip(z) => z.finish().map_err(|e| e.to_string())?,
        };
        w.flush().map_err(|e| e.to_string())?;
        let file = w.into_inner().map_err(|e| e.error().to_string())?;
        file.sync_all().map_err(|e| e.to_string())?;
        Ok(count)
    }
}

impl mbfg::forward::StepSink for Streamed {
    fn step(&mut self, t: f64, q: &[f64], dq: &[f64], ddq: &[f64]) -> mbfg::Result<()> {
        let rows = self.rows.as_mut().expect("an open stream");
        match rows.sample(t, q, dq, ddq) {
            Ok(()) => Ok(()),
            // A non-finite value is the run's to report; a write error is the file's.
            Err(e @ mbfg::Error::Singular { .. }) => Err(e),
            Err(e) => Err(self.error(e)),
        }
    }

    fn restart(&mut self) -> mbfg::Result<()> {
        self.open()
    }
}

/// `run.csv` → `run.partial.csv`, `run.csv.gz` → `run.partial.csv.gz` (beside it).
pub fn partial_path(target: &Path) -> PathBuf {
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let (name, gz) = match name.strip_suffix(".gz") {
        Some(stem) => (stem, ".gz"),
        None => (name.as_str(), ""),
    };
    let stem = name.strip_suffix(".csv").unwrap_or(name);
    target.with_file_name(format!("{stem}.partial.csv{gz}"))
}

/// Whether the output is written gzip-compressed: by its name, as `read_table`
/// reads it.
fn is_gzip(target: &Path) -> bool {
    target.extension().is_some_and(|e| e == "gz")
}

/// The rows `body` writes, then the line `# incomplete: why`, flushed.
fn marked(
    w: &mut dyn Write,
    body: &dyn Fn(&mut dyn Write) -> mbfg::Result<()>,
    why: &str,
) -> Result<(), String> {
    body(w).map_err(|e| e.to_string())?;
    writeln!(w, "# incomplete: {}", one_line(why)).map_err(|e| e.to_string())?;
    w.flush().map_err(|e| e.to_string())
}

/// Removes the temporary files of `target` that runs no longer alive left beside it
/// (killed, or out of memory, before they could clean up).
fn remove_stale_temps(target: &Path) {
    let Some(name) = target.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return;
    };
    let dir = match target.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    // Whether a process is alive is read from /proc: without it, nothing is removed.
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return;
    };
    if !Path::new("/proc/self").exists() {
        return;
    }
    let prefix = format!(".{name}.");
    for entry in entries.flatten() {
        let file = entry.file_name().to_string_lossy().into_owned();
        let pid = file
            .strip_prefix(&prefix)
            .and_then(|rest| rest.strip_suffix(".tmp"))
            .and_then(|pid| pid.parse::<u32>().ok());
        if let Some(pid) = pid {
            let alive = pid == std::process::id() || Path::new(&format!("/proc/{pid}")).exists();
            if !alive {
                std::fs::remove_file(entry.path()).ok();
            }
        }
    }
}

/// A hidden name in the target's directory, unique to this process.
fn temp_beside(target: &Path) -> PathBuf {
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    target.with_file_name(format!(".{name}.{}.tmp", std::process::id()))
}

fn write_file(
    path: &Path,
    gzip: bool,
    body: &dyn Fn(&mut dyn Write) -> mbfg::Result<()>,
) -> Result<(), String> {
    let file = File::options()
        .write(true)
        .truncate(true)
        .open(path)
        .map_err(|e| e.to_string())?;
    let w = encode(std::io::BufWriter::new(file), gzip, body)?;
    let file = w.into_inner().map_err(|e| e.error().to_string())?;
    // On disk before the rename, so that a crash cannot leave a renamed empty file.
    file.sync_all().map_err(|e| e.to_string())
}

/// Writes the CSV `body` makes into `w`, through a gzip encoder if asked (finished,
/// so that the stream is complete), and gives `w` back flushed.
fn encode<W: Write>(
    mut w: W,
    gzip: bool,
    body: &dyn Fn(&mut dyn Write) -> mbfg::Result<()>,
) -> Result<W, String> {
    if gzip {
        let mut z = flate2::write::GzEncoder::new(w, flate2::Compression::default());
        body(&mut z).map_err(|e| e.to_string())?;
        w = z.finish().map_err(|e| e.to_string())?;
    } else {
        body(&mut w).map_err(|e| e.to_string())?;
    }
    w.flush().map_err(|e| e.to_string())?;
    Ok(w)
}

/// Whether two paths name the same existing file.
fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

fn one_line(text: &str) -> String {
    text.replace(['\n', '\r'], " ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn partial_files_sit_beside_the_target() {
        assert_eq!(
            partial_path(Path::new("out/run.csv")),
            PathBuf::from("out/run.partial.csv")
        );
        assert_eq!(
            partial_path(Path::new("run")),
            PathBuf::from("run.partial.csv")
        );
        assert_eq!(
            partial_path(Path::new("out/run.csv.gz")),
            PathBuf::from("out/run.partial.csv.gz")
        );
        assert_eq!(
            partial_path(Path::new("run.gz")),
            PathBuf::from("run.partial.csv.gz")
        );
    }

    #[test]
    fn gzip_output_reads_back() {
        let tr = Trajectory {
            names: vec!["a".into()],
            t: vec![0.0, 0.5],
            q: vec![1.0, 2.0],
            dq: vec![0.0; 2],
            ddq: vec![0.0; 2],
        };
        let target = std::env::temp_dir().join(format!("mbfg-out-{}.csv.gz", std::process::id()));
        let output = Output::open(Some(&target), &[]).unwrap();
        output.commit(&tr, &CsvOptions::default()).unwrap();
        let bytes = std::fs::read(&target).unwrap();
        let table = mbfg::io::read_table(&target).unwrap();
        std::fs::remove_file(&target).ok();
        assert_eq!(&bytes[..2], &[0x1f, 0x8b], "not gzip");
        assert_eq!(table.column("q:a").unwrap(), [1.0, 2.0]);
    }
}
