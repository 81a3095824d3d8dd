//! The result logs: where the next record of each pass's log goes, and the recycling of logs
//! no pass writes any more (kept as spares for the next new log).

use super::files::Paths;
use super::log_file::{self, LogFile};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Mutex;

/// Where the next record of each result log goes (`Paths::result_log`).
///
/// A log is not deleted and written afresh each pass but rewritten in place, from its start,
/// by the pass two after the one it held, once that pass is recorded (no merge reads it any
/// more; `jobs::ensure_passes` creates a pass's tasks only once the pass two before it is
/// recorded). A log no later pass of its job will write is not deleted either but kept as a
/// spare (up to `SPARE_LOGS` of them, in `Paths::spare_logs`), which the next new log takes
/// instead of a new file, as PostgreSQL recycles its WAL segments: a file written afresh takes
/// new page-cache pages, each faulted in (on a virtual machine that hands freed memory back to
/// its host, on the host too), which matters where a file system refuses direct I/O and the
/// logs go through the page cache (`log_file`). Records are not fsync'd: a record damaged by a
/// power cut (or found holding an older pass's bytes) fails its checksums when merged, and its
/// task is rendered again.
#[derive(Default)]
pub(crate) struct ResultLogs {
    /// Per job, per log (pass parity): the pass writing it now and where its records end.
    cursors: Mutex<HashMap<String, [Option<LogCursor>; 2]>>,
}

/// Spare result logs kept at most, and their bytes at most (a log is as long as the longest
/// pass's results it held; a longer one is deleted).
const SPARE_LOGS: usize = 4;
const SPARE_LOG_BYTES: u64 = 4 << 30;

#[derive(Clone, Copy)]
struct LogCursor {
    pass: u32,
    end: u64,
}

impl ResultLogs {
    /// Writes `bytes`, a result of pass `pass` of job `job` (whose tile checkpoints hold
    /// `recorded` passes: no merge reads an earlier pass's results), into its log and returns
    /// where they lie. They go after the pass's last record; at the start of the log when the
    /// pass is the first to write it since the checkpoints hold the pass it held; and at the end
    /// of the file when this process does not know the log (after a restart), when the pass it
    /// holds is still read, or when the result is of an older pass than the log's (a stale
    /// attempt, which the store will refuse, or a result rendered again because its record was
    /// found damaged). One write at a time: every log's cursor is held meanwhile.
    pub fn write(
        &self,
        paths: &Paths,
        job: &str,
        pass: u32,
        recorded: u32,
        bytes: &[u8],
    ) -> std::io::Result<std::ops::Range<u64>> {
        let mut cursors = self.cursors.lock().unwrap_or_else(|e| e.into_inner());
        let slot = &mut cursors.entry(job.to_string()).or_default()[(pass % 2) as usize];
        let path = paths.result_log(job, pass);
        // Records start at multiples of `log_file::ALIGN` (direct I/O).
        let file_end = || match std::fs::metadata(&path) {
            Ok(m) => Ok(log_file::align_up(m.len())),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(0),
            Err(e) => Err(e),
        };
        let (at, moves) = match *slot {
            Some(c) if c.pass == pass => (c.end, true),
            Some(c) if c.pass < pass && recorded > c.pass => (0, true),
            Some(c) if c.pass > pass => (file_end()?, false),
            _ => match file_end()? {
                // A new log: a spare's old bytes are never read (no record points there).
                0 => {
                    take_spare(paths, &path);
                    (0, true)
                }
                end => (end, true),
            },
        };
        LogFile::open_write(&path)?.write_at(at, bytes)?;
        let end = at + bytes.len() as u64;
        if moves {
            *slot = Some(LogCursor {
                pass,
                end: log_file::align_up(end),
            });
        }
        Ok(at..end)
    }

    /// Gives up the log of recorded pass `pass` of job `job` when no later pass of the job will
    /// write it (`reused`: false): kept as a spare for another job's, or deleted (`retire`);
    /// else it waits for pass `pass + 2`.
    pub fn release(&self, paths: &Paths, job: &str, pass: u32, reused: bool) {
        if reused {
            return;
        }
        let mut cursors = self.cursors.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(logs) = cursors.get_mut(job) {
            logs[(pass % 2) as usize] = None;
        }
        retire(paths, &paths.result_log(job, pass));
    }

    /// Forgets where job `job`'s logs end, leaving them on disk (a failed job's, which a
    /// requeue goes on from: its next records go at the logs' ends, as after a restart).
    pub fn forget(&self, job: &str) {
        self.cursors
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(job);
    }

    /// Forgets job `job`'s logs (it ended) and keeps them as spares.
    pub fn remove(&self, paths: &Paths, job: &str) {
        let mut cursors = self.cursors.lock().unwrap_or_else(|e| e.into_inner());
        cursors.remove(job);
        for parity in 0..2 {
            retire(paths, &paths.result_log(job, parity));
        }
    }
}

/// Moves a spare log (if there is one) to `path`, which does not exist.
fn take_spare(paths: &Paths, path: &Path) {
    let Ok(dir) = std::fs::read_dir(paths.spare_logs()) else {
        return;
    };
    if path
        .parent()
        .is_some_and(|p| std::fs::create_dir_all(p).is_err())
    {
        return;
    }
    for spare in dir.flatten() {
        if std::fs::rename(spare.path(), path).is_ok() {
            return;
        }
    }
}

/// Keeps the log at `path` as a spare, or deletes it when `SPARE_LOGS` are kept already or it
/// would take the spares past `SPARE_LOG_BYTES`.
fn retire(paths: &Paths, path: &Path) {
    let Ok(len) = std::fs::metadata(path).map(|m| m.len()) else {
        return;
    };
    let dir = paths.spare_logs();
    let spares: Vec<u64> = std::fs::read_dir(&dir).map_or(Vec::new(), |d| {
        d.flatten()
            .map(|e| e.metadata().map_or(0, |m| m.len()))
            .collect()
    });
    if spares.len() < SPARE_LOGS
        && spares.iter().sum::<u64>() + len <= SPARE_LOG_BYTES
        && std::fs::create_dir_all(&dir).is_ok()
        && std::fs::rename(path, dir.join(format!("{}.log", uuid::Uuid::new_v4()))).is_ok()
    {
        return;
    }
    let _ = std::fs::remove_file(path);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pass's results follow one another in its log; the pass two later rewrites the log from
    /// its start only once the pass it held is recorded; a stale attempt of an older pass and
    /// a process that does not know the log (a restart) write after everything in the file, so
    /// no record a merge may still read is ever overwritten.
    #[test]
    fn result_logs_are_rewritten_in_place_only_once_their_pass_is_recorded() {
        let dir = std::env::temp_dir().join(format!("omis-logs-{}", uuid::Uuid::new_v4()));
        let paths = Paths { root: dir.clone() };
        let logs = ResultLogs::default();
        let read = |pass: u32, r: &std::ops::Range<u64>| {
            let bytes = std::fs::read(paths.result_log("j", pass)).expect("log");
            bytes[r.start as usize..r.end as usize].to_vec()
        };
        let w = |pass: u32, recorded: u32, b: &[u8]| {
            logs.write(&paths, "j", pass, recorded, b).expect("write")
        };
        // Records start at multiples of ALIGN (direct I/O pads each one up to the next).
        const A: u64 = log_file::ALIGN;
        // Pass 0 and pass 1 (each in its own log) while pass 0 is merged.
        assert_eq!(w(0, 0, b"aaaa"), 0..4);
        assert_eq!(w(0, 0, b"bb"), A..A + 2);
        assert_eq!(w(1, 0, b"cccc"), 0..4);
        // Pass 2 before pass 0 is recorded (ensure_passes never lets it, but if it did): after
        // pass 0's records.
        assert_eq!(w(2, 0, b"dd"), 2 * A..2 * A + 2);
        assert_eq!(read(0, &(0..4)), b"aaaa");
        // Once pass 0 is recorded, pass 2 begins the log again.
        let logs2 = ResultLogs::default();
        let w2 = |pass: u32, recorded: u32, b: &[u8]| {
            logs2.write(&paths, "j", pass, recorded, b).expect("write")
        };
        // (A process that does not know the log writes after its end: three records so far.)
        assert_eq!(w2(0, 0, b"ee"), 3 * A..3 * A + 2);
        assert_eq!(w2(2, 1, b"ffff"), 0..4);
        assert_eq!(w2(2, 1, b"g"), A..A + 1);
        assert_eq!(read(2, &(0..4)), b"ffff");
        assert_eq!(read(2, &(A..A + 1)), b"g");
        // A late attempt of pass 0 goes after the end and leaves pass 2's place alone.
        assert_eq!(w2(0, 1, b"hh"), 4 * A..4 * A + 2);
        assert_eq!(w2(2, 1, b"i"), 2 * A..2 * A + 1);
        assert_eq!(read(2, &(0..4)), b"ffff");
        assert_eq!(read(2, &(A..A + 1)), b"g");
        assert_eq!(read(2, &(2 * A..2 * A + 1)), b"i");
        // A recorded pass no later pass writes gives its log up at once, the others when the
        // job ends: kept as spares, which the next new logs take (and write from their start).
        let spares = || std::fs::read_dir(paths.spare_logs()).map_or(0, |d| d.count());
        logs2.release(&paths, "j", 1, false);
        assert!(!paths.result_log("j", 1).exists());
        logs2.release(&paths, "j", 2, true);
        assert!(paths.result_log("j", 2).exists());
        logs2.remove(&paths, "j");
        assert!(!paths.result_log("j", 0).exists());
        assert_eq!(spares(), 2);
        for job in ["k", "l", "m"] {
            assert_eq!(logs2.write(&paths, job, 0, 0, b"n").expect("write"), 0..1);
        }
        assert_eq!(spares(), 0);
        // (Padded to ALIGN with direct I/O, not where the file system refuses it.)
        let len = |job: &str| {
            log_file::align_up(
                std::fs::metadata(paths.result_log(job, 0))
                    .expect("log")
                    .len(),
            )
        };
        let mut taken = [len("k"), len("l")];
        taken.sort_unstable();
        assert_eq!(
            (taken, len("m")),
            ([A, 5 * A], A),
            "the two spares, then a new log"
        );
        // At most SPARE_LOGS are kept; the rest are deleted.
        for j in 0..SPARE_LOGS + 2 {
            let path = dir.join(format!("extra-{j}.log"));
            std::fs::write(&path, b"p").expect("a log");
            retire(&paths, &path);
            assert!(!path.exists());
        }
        assert_eq!(spares(), SPARE_LOGS);
        // Nor past SPARE_LOG_BYTES (a sparse file: no disk is written).
        let spare = std::fs::read_dir(paths.spare_logs())
            .expect("spares")
            .flatten()
            .next()
            .expect("a spare")
            .path();
        std::fs::remove_file(&spare).expect("one spare fewer");
        let big = dir.join("big.log");
        std::fs::File::create(&big)
            .and_then(|f| f.set_len(SPARE_LOG_BYTES))
            .expect("a sparse log");
        retire(&paths, &big);
        assert!(!big.exists());
        assert_eq!(spares(), SPARE_LOGS - 1);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
