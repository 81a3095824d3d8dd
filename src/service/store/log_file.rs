//! A result log's file, written and read around the page cache (`O_DIRECT` on Linux), as
//! databases write their logs.
//!
//! A pass's results are written once, read once by its merge tasks, and then rewritten by a
//! later pass: keeping them in the page cache buys nothing, and copying them into it and out of
//! it was the coordinator's largest kernel cost. On the benchmark VM, whose free memory goes
//! back to its host, 850 MB written through the page cache into a new file took 1.4-2.8 s of
//! system time and read back uncached 0.8 s, against 0.08 s and 0.05 s with `O_DIRECT`
//! (BENCHMARKS.md, "The render service"). Direct I/O needs offsets, lengths and memory aligned to the
//! device's logical block: records start at multiples of [`ALIGN`], a write is padded with
//! zeros to one, and bytes go through a per-thread aligned buffer of [`CHUNK`] bytes. Where the
//! file system refuses `O_DIRECT` or an aligned transfer, the file is read and written through
//! the page cache as before. A direct transfer is an I/O of its own (on the VM, a doorbell
//! write that exits to the host: 4-5 % of an optimal-MIS job's coordinator CPU); the tile
//! checkpoints, tried the same way, gained nothing measurable and stay in the page cache.

use std::cell::RefCell;
use std::fs::{File, OpenOptions};
use std::io;
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::Path;

/// Records start at multiples of this: the largest logical block size direct I/O asks for.
pub(crate) const ALIGN: u64 = 4096;

/// Bytes moved per system call, through the aligned buffer (one per thread that uses it).
const CHUNK: usize = 1 << 20;

/// `n` rounded up to a multiple of [`ALIGN`].
pub(crate) fn align_up(n: u64) -> u64 {
    n.div_ceil(ALIGN) * ALIGN
}

/// One aligned block of the scratch buffer.
#[repr(C, align(4096))]
#[derive(Clone, Copy)]
struct Block([u8; ALIGN as usize]);

thread_local! {
    static SCRATCH: RefCell<Vec<Block>> = const { RefCell::new(Vec::new()) };
}

/// Runs `f` on this thread's aligned buffer of [`CHUNK`] bytes.
fn with_scratch<R>(f: impl FnOnce(&mut [u8]) -> R) -> R {
    SCRATCH.with_borrow_mut(|v| {
        if v.is_empty() {
            v.resize(CHUNK / ALIGN as usize, Block([0; ALIGN as usize]));
        }
        // SAFETY: `Block` is `repr(C)` plain bytes, so the blocks are `len * ALIGN` initialised
        // bytes in a row; the slice borrows `v` mutably for as long as it lives.
        let bytes = unsafe {
            std::slice::from_raw_parts_mut(v.as_mut_ptr().cast::<u8>(), v.len() * ALIGN as usize)
        };
        f(bytes)
    })
}

/// Whether `e` is the file system refusing direct I/O (or an alignment it needs).
fn refused(e: &io::Error) -> bool {
    e.raw_os_error() == Some(libc::EINVAL)
}

/// An open result log.
pub(crate) struct LogFile {
    file: File,
    /// Opened with `O_DIRECT` and not refused since.
    direct: bool,
}

impl LogFile {
    /// Opens the log at `path` for reading.
    pub fn open_read(path: &Path) -> io::Result<LogFile> {
        Self::open(path, OpenOptions::new().read(true))
    }

    /// Opens the log at `path` for writing, creating it (and its folder) when missing.
    pub fn open_write(path: &Path) -> io::Result<LogFile> {
        let mut o = OpenOptions::new();
        o.write(true).create(true).truncate(false);
        super::files::open_creating(path, |p| Self::open(p, &o))
    }

    fn open(path: &Path, options: &OpenOptions) -> io::Result<LogFile> {
        #[cfg(target_os = "linux")]
        {
            use std::os::unix::fs::OpenOptionsExt;
            match options.clone().custom_flags(libc::O_DIRECT).open(path) {
                Ok(file) => return Ok(LogFile { file, direct: true }),
                Err(e) if refused(&e) => {}
                Err(e) => return Err(e),
            }
        }
        Ok(LogFile {
            file: options.open(path)?,
            direct: false,
        })
    }

    /// The file's length in bytes.
    pub fn len(&self) -> io::Result<u64> {
        Ok(self.file.metadata()?.len())
    }

    /// Goes on through the page cache (the file system refused an aligned transfer).
    fn buffered(&mut self) -> io::Result<()> {
        self.direct = false;
        #[cfg(target_os = "linux")]
        {
            use std::os::fd::AsRawFd;
            let fd = self.file.as_raw_fd();
            // SAFETY: fcntl on a descriptor this file owns; it reads no memory of ours.
            let flags = unsafe { libc::fcntl(fd, libc::F_GETFL) };
            // SAFETY: as above.
            if flags < 0 || unsafe { libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_DIRECT) } < 0 {
                return Err(io::Error::last_os_error());
            }
        }
        Ok(())
    }

    /// Writes `bytes` at `at`, a multiple of [`ALIGN`]; with direct I/O the bytes after them
    /// up to the next multiple become zeros, so nothing may lie there.
    pub fn write_at(&mut self, at: u64, bytes: &[u8]) -> io::Result<()> {
        debug_assert_eq!(at % ALIGN, 0, "records start at multiples of ALIGN");
        if self.direct {
            match self.write_direct(at, bytes) {
                Err(e) if refused(&e) => self.buffered()?,
                r => return r,
            }
        }
        self.file.write_all_at(bytes, at)
    }

    fn write_direct(&self, at: u64, bytes: &[u8]) -> io::Result<()> {
        with_scratch(|s| {
            for (k, piece) in bytes.chunks(CHUNK).enumerate() {
                let n = align_up(piece.len() as u64) as usize;
                s[..piece.len()].copy_from_slice(piece);
                s[piece.len()..n].fill(0);
                self.file.write_all_at(&s[..n], at + (k * CHUNK) as u64)?;
            }
            Ok(())
        })
    }

    /// Appends bytes `range` of the file to `buf` and returns where they begin in it; an
    /// `UnexpectedEof` error (and `buf` as it was) when the file ends before `range` does.
    pub fn read_into(&mut self, range: &Range<u64>, buf: &mut Vec<u8>) -> io::Result<usize> {
        if range.start > range.end {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("bytes {range:?} of a log"),
            ));
        }
        let at = buf.len();
        buf.reserve((range.end - range.start) as usize);
        let read = match self.direct {
            true => match self.read_direct(range, buf) {
                Err(e) if refused(&e) => {
                    buf.truncate(at);
                    self.buffered()
                        .and_then(|()| self.read_buffered(range, buf))
                }
                r => r,
            },
            false => self.read_buffered(range, buf),
        };
        if let Err(e) = read {
            buf.truncate(at);
            return Err(e);
        }
        Ok(at)
    }

    fn read_buffered(&self, range: &Range<u64>, buf: &mut Vec<u8>) -> io::Result<()> {
        let at = buf.len();
        buf.resize(at + (range.end - range.start) as usize, 0);
        self.file.read_exact_at(&mut buf[at..], range.start)
    }

    fn read_direct(&self, range: &Range<u64>, buf: &mut Vec<u8>) -> io::Result<()> {
        with_scratch(|s| {
            let mut pos = range.start;
            while pos < range.end {
                let base = pos / ALIGN * ALIGN;
                let want = (align_up(range.end) - base).min(CHUNK as u64) as usize;
                // A short read ends the file (direct reads return whole blocks until its end).
                let mut got = 0;
                while got < want {
                    let n = self.file.read_at(&mut s[got..want], base + got as u64)?;
                    got += n;
                    if n == 0 || !(n as u64).is_multiple_of(ALIGN) {
                        break;
                    }
                }
                let end = ((range.end - base) as usize).min(got);
                let skip = (pos - base) as usize;
                if end <= skip {
                    return Err(io::Error::new(
                        io::ErrorKind::UnexpectedEof,
                        format!("the log ends before byte {}", range.end),
                    ));
                }
                buf.extend_from_slice(&s[skip..end]);
                pos = base + end as u64;
            }
            Ok(())
        })
    }

    /// A reader of bytes `range` of the file, fetched a piece at a time (for an index at the
    /// start of a record whose length is not known before it is read).
    pub fn reader(&mut self, range: Range<u64>) -> RangeReader<'_> {
        RangeReader {
            log: self,
            pos: range.start,
            end: range.end,
            buf: Vec::new(),
            at: 0,
        }
    }
}

/// See [`LogFile::reader`].
pub(crate) struct RangeReader<'a> {
    log: &'a mut LogFile,
    pos: u64,
    end: u64,
    buf: Vec<u8>,
    at: usize,
}

impl io::Read for RangeReader<'_> {
    fn read(&mut self, out: &mut [u8]) -> io::Result<usize> {
        const PIECE: u64 = 16 << 10;
        if self.at == self.buf.len() {
            if self.pos == self.end {
                return Ok(0);
            }
            let next = self.end.min(self.pos + PIECE);
            self.buf.clear();
            self.log.read_into(&(self.pos..next), &mut self.buf)?;
            self.pos = next;
            self.at = 0;
        }
        let n = out.len().min(self.buf.len() - self.at);
        out[..n].copy_from_slice(&self.buf[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;

    /// Records written at aligned offsets read back exactly from any range, across the
    /// buffer's chunks, with direct I/O and through the page cache (where a file system
    /// refuses it); a range past the end of the file is an error that leaves the buffer as
    /// it was.
    #[test]
    fn records_read_back_from_any_range() {
        for buffered in [false, true] {
            let dir = std::env::temp_dir().join(format!("omis-log-file-{}", uuid::Uuid::new_v4()));
            let path = dir.join("sub").join("results.log");
            let open = |w: bool| {
                let mut f = match w {
                    true => LogFile::open_write(&path).expect("created with its folder"),
                    false => LogFile::open_read(&path).expect("open"),
                };
                if buffered {
                    f.buffered().expect("through the page cache");
                }
                f
            };
            let record = |seed: u32, n: usize| -> Vec<u8> {
                (0..n as u32)
                    .map(|i| (i.wrapping_mul(2_654_435_761) ^ seed) as u8)
                    .collect()
            };
            let a = record(1, 10_000);
            let b = record(2, CHUNK * 2 + 123);
            let mut w = open(true);
            w.write_at(0, &a).expect("write a");
            let at_b = align_up(a.len() as u64);
            w.write_at(at_b, &b).expect("write b");
            let mut r = open(false);
            let mut buf = b"head".to_vec();
            for (range, want) in [
                (0..a.len() as u64, &a[..]),
                (17..4099, &a[17..4099]),
                (at_b..at_b + b.len() as u64, &b[..]),
                (at_b + 5000..at_b + CHUNK as u64 + 9, &b[5000..CHUNK + 9]),
            ] {
                buf.truncate(4);
                let at = r.read_into(&range, &mut buf).expect("read");
                assert_eq!(at, 4);
                assert_eq!(&buf[4..], want, "{range:?}, buffered {buffered}");
            }
            let mut via_reader = Vec::new();
            r.reader(at_b + 1..at_b + 200_001)
                .read_to_end(&mut via_reader)
                .expect("reader");
            assert_eq!(via_reader, &b[1..200_001]);
            // Rewritten in place from the start, shorter: the old bytes after it stay unread.
            w.write_at(0, &b"new"[..]).expect("rewrite");
            buf.clear();
            r.read_into(&(0..3), &mut buf).expect("read");
            assert_eq!(buf, b"new");
            let end = at_b + b.len() as u64;
            buf.clear();
            buf.extend_from_slice(b"kept");
            let e = r
                .read_into(&(end - 10..end + 10_000), &mut buf)
                .expect_err("past the end");
            assert_eq!(e.kind(), io::ErrorKind::UnexpectedEof);
            assert_eq!(buf, b"kept");
            // A range that ends before it begins (a damaged index) is an error, not a panic.
            #[allow(clippy::reversed_empty_ranges)]
            let backwards = 10..5;
            assert!(r.read_into(&backwards, &mut buf).is_err());
            assert_eq!(buf, b"kept");
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
}
