//! Retention: a periodic sweep that deletes finished jobs (`jobs::delete`, rows and files)
//! older than `Config::keep_finished_s` and, while the data folder is over
//! `Config::store_budget_bytes`, the finished jobs that ended first. Active jobs are never
//! touched. Every deletion is logged.

use super::{App, jobs, store};
use std::path::Path;
use std::sync::Arc;

/// Bytes of the files under `dir` (what they hold, not the blocks they take), symbolic links
/// not followed.
pub(crate) fn folder_bytes(dir: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => folder_bytes(&e.path()),
            Ok(t) if t.is_file() => e.metadata().map_or(0, |m| m.len()),
            _ => 0,
        })
        .sum()
}

/// One sweep: what it deleted (job ids), oldest first.
pub(crate) fn sweep(app: &App) -> Vec<String> {
    let (keep_s, budget) = (app.cfg.keep_finished_s, app.cfg.store_budget_bytes);
    if keep_s.is_none() && budget.is_none() {
        return Vec::new();
    }
    let finished = match app.db().finished_jobs() {
        Ok(f) => f,
        Err(e) => {
            tracing::error!("retention: cannot list finished jobs: {e}");
            return Vec::new();
        }
    };
    let now = store::now();
    let mut deleted = Vec::new();
    let mut delete = |job: &store::JobRow, why: &str| match jobs::delete(app, &job.id) {
        Ok(store::Deleted::Removed(_)) => {
            tracing::info!(
                "retention: deleted job {} ({}{}, ended {:.0} s ago): {why}",
                job.id,
                job.state,
                job.name
                    .as_deref()
                    .map(|n| format!(", '{n}'"))
                    .unwrap_or_default(),
                now - job.finished_at.unwrap_or(job.created_at)
            );
            deleted.push(job.id.clone());
            true
        }
        Ok(_) => false,
        Err(e) => {
            tracing::error!("retention: cannot delete job {}: {e}", job.id);
            false
        }
    };
    let mut left = Vec::new();
    for job in finished {
        let ended = job.finished_at.unwrap_or(job.created_at);
        match keep_s {
            Some(keep) if now - ended > keep => {
                delete(
                    &job,
                    &format!("finished more than {keep:.0} s ago (--keep-finished)"),
                );
            }
            _ => left.push(job),
        }
    }
    if let Some(budget) = budget {
        // The spare result logs first: a cache of files for the next job's logs, no one's data.
        let used = folder_bytes(&app.paths.root);
        let spares = app.paths.spare_logs();
        if used > budget && spares.is_dir() {
            tracing::info!(
                "retention: the data folder holds {used} bytes, over the budget of {budget} \
                 (--store-budget): removing the spare result logs ({} bytes)",
                folder_bytes(&spares)
            );
            let _ = std::fs::remove_dir_all(&spares);
        }
        for job in &left {
            let used = folder_bytes(&app.paths.root);
            if used <= budget {
                break;
            }
            delete(
                job,
                &format!(
                    "the data folder holds {used} bytes, over the budget of {budget} (--store-budget)"
                ),
            );
        }
    }
    deleted
}

/// Sweeps every `Config::sweep_interval_s` (on a blocking thread), from the start.
pub(crate) async fn sweeper(app: Arc<App>) {
    if app.cfg.keep_finished_s.is_none() && app.cfg.store_budget_bytes.is_none() {
        return;
    }
    let every = std::time::Duration::from_secs_f64(app.cfg.sweep_interval_s.max(0.1));
    let mut tick = tokio::time::interval(every);
    loop {
        tick.tick().await;
        let a = app.clone();
        let _ = tokio::task::spawn_blocking(move || sweep(&a)).await;
    }
}

/// A size such as `20G`, `512M`, `1.5T` or `4096` (bytes; K, M, G, T are powers of 1024, an
/// optional `B` or `iB` after them).
pub(crate) fn parse_size(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let upper = t.to_ascii_uppercase();
    let digits = upper
        .trim_end_matches("IB")
        .trim_end_matches('B')
        .trim_end();
    let (num, scale) = match digits.chars().last() {
        Some('K') => (&digits[..digits.len() - 1], 1u64 << 10),
        Some('M') => (&digits[..digits.len() - 1], 1 << 20),
        Some('G') => (&digits[..digits.len() - 1], 1 << 30),
        Some('T') => (&digits[..digits.len() - 1], 1 << 40),
        _ => (digits, 1),
    };
    let v: f64 = num
        .trim()
        .parse()
        .map_err(|_| format!("'{s}' is not a size such as 20G, 512M or 4096"))?;
    if !(v.is_finite() && v >= 0.0) || v * scale as f64 > u64::MAX as f64 {
        return Err(format!("'{s}' is not a size such as 20G, 512M or 4096"));
    }
    Ok((v * scale as f64) as u64)
}

#[cfg(test)]
mod tests {
    use super::parse_size;

    #[test]
    fn sizes_parse_with_binary_units() {
        assert_eq!(parse_size("4096"), Ok(4096));
        assert_eq!(parse_size("20G"), Ok(20 << 30));
        assert_eq!(parse_size("512mb"), Ok(512 << 20));
        assert_eq!(parse_size("1.5KiB"), Ok(1536));
        assert!(parse_size("lots").is_err());
        assert!(parse_size("-1G").is_err());
        assert!(parse_size("").is_err());
    }
}
