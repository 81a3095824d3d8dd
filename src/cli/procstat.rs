//! What the benchmarks read about processes from Linux's /proc: CPU time and memory, of this
//! process or of another one (a coordinator or worker the benchmark started).

/// (VmRSS, VmHWM) of process `pid` (or this process for `None`) in bytes; 0 where unavailable.
pub fn memory(pid: Option<u32>) -> (u64, u64) {
    let path = match pid {
        Some(p) => format!("/proc/{p}/status"),
        None => "/proc/self/status".to_string(),
    };
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let get = |key: &str| {
        text.lines()
            .find(|l| l.starts_with(key))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<u64>().ok())
            .map_or(0, |kb| kb * 1024)
    };
    (get("VmRSS:"), get("VmHWM:"))
}

/// Peak resident memory of this process so far (VmHWM), in MiB; NaN where unavailable.
pub fn peak_rss_mib() -> f64 {
    match memory(None).1 {
        0 => f64::NAN,
        b => b as f64 / (1024.0 * 1024.0),
    }
}

/// User + system CPU seconds of process `pid` (from /proc/PID/stat, in clock ticks), or of this
/// process and all its threads for `None` (getrusage, in microseconds); NaN where unavailable.
pub fn cpu_seconds(pid: Option<u32>) -> f64 {
    let Some(pid) = pid else {
        // SAFETY: getrusage writes into the zeroed struct we own.
        let mut r: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut r) } != 0 {
            return f64::NAN;
        }
        let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
        return t(r.ru_utime) + t(r.ru_stime);
    };
    usage(pid).map_or(f64::NAN, |u| u.cpu_s())
}

/// What a process has used so far: CPU time in user mode and in the kernel (on its behalf:
/// system calls, and page faults, which a virtual machine that hands freed memory back to its
/// host makes costly), and minor page faults.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ProcUse {
    pub user_s: f64,
    pub sys_s: f64,
    pub minor_faults: u64,
}

impl ProcUse {
    /// What was used between `before` and this reading.
    pub fn since(self, before: ProcUse) -> ProcUse {
        ProcUse {
            user_s: self.user_s - before.user_s,
            sys_s: self.sys_s - before.sys_s,
            minor_faults: self.minor_faults.saturating_sub(before.minor_faults),
        }
    }

    /// CPU seconds, user and kernel.
    pub fn cpu_s(&self) -> f64 {
        self.user_s + self.sys_s
    }
}

/// What process `pid` has used since reading `before` (None where either reading is missing).
pub fn usage_since(pid: u32, before: Option<ProcUse>) -> Option<ProcUse> {
    Some(usage(pid)?.since(before?))
}

/// What process `pid` has used so far (from /proc/PID/stat), or None where unavailable.
pub fn usage(pid: u32) -> Option<ProcUse> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name (which may contain spaces) start after the last ')'.
    let rest = text.rsplit_once(')')?.1;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // minflt, utime and stime are fields 10, 14 and 15 of the whole line, 7, 11 and 12 after
    // the name.
    let field = |i: usize| fields.get(i).and_then(|v| v.parse::<u64>().ok());
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    if hz <= 0 {
        return None;
    }
    Some(ProcUse {
        user_s: field(11)? as f64 / hz as f64,
        sys_s: field(12)? as f64 / hz as f64,
        minor_faults: field(7)?,
    })
}

/// The processes whose parent is `pid` (from /proc/*/stat).
pub fn children(pid: u32) -> Vec<u32> {
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    dir.filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|&p| {
            std::fs::read_to_string(format!("/proc/{p}/stat"))
                .ok()
                .and_then(|t| {
                    // The parent pid is the second field after the command name.
                    let rest = t.rsplit_once(')')?.1.to_string();
                    rest.split_whitespace().nth(1)?.parse::<u32>().ok()
                })
                == Some(pid)
        })
        .collect()
}

/// CPU seconds of process `pid` and of its children that are alive now (a coordinator and the
/// local workers it started).
pub fn cpu_seconds_with_children(pid: u32) -> f64 {
    cpu_seconds(Some(pid))
        + children(pid)
            .into_iter()
            .map(|c| cpu_seconds(Some(c)))
            .filter(|v| v.is_finite())
            .sum::<f64>()
}

/// Bytes process `pid` caused to be written to storage (write_bytes of /proc/PID/io); 0 where
/// unavailable.
pub fn write_bytes(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/io"))
        .unwrap_or_default()
        .lines()
        .find_map(|l| l.strip_prefix("write_bytes:"))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn this_process_uses_cpu_and_memory() {
        let t0 = cpu_seconds(None);
        let mut x = 0u64;
        // Spin until this process has used 0.2 s more CPU (or 20 s passed on a loaded machine).
        let start = std::time::Instant::now();
        while cpu_seconds(None) < t0 + 0.2 && start.elapsed().as_secs() < 20 {
            for _ in 0..10_000 {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
            }
        }
        std::hint::black_box(x);
        let t1 = cpu_seconds(None);
        assert!(t1 >= t0 + 0.2, "{t0} -> {t1}");
        assert!(peak_rss_mib() > 0.5);
        let (rss, hwm) = memory(Some(std::process::id()));
        assert!(rss > 0 && hwm >= rss);
        // /proc counts ticks: at least 0.1 s of the 0.2 s spun above.
        assert!(cpu_seconds(Some(std::process::id())) >= 0.1);
    }

    #[test]
    fn touching_new_pages_counts_minor_faults() {
        let pid = std::process::id();
        let before = usage(pid).expect("/proc/self/stat");
        // 64 MiB from mmap (above glibc's threshold), one write per 4 KiB page: each page is a
        // fault of this process.
        let mut v = vec![0u8; 64 << 20];
        for b in v.iter_mut().step_by(4096) {
            *b = 1;
        }
        std::hint::black_box(&v);
        let used = usage(pid).expect("/proc/self/stat").since(before);
        assert!(used.minor_faults >= 8192, "{used:?}");
        assert!(used.user_s >= 0.0 && used.sys_s >= 0.0, "{used:?}");
    }
}
