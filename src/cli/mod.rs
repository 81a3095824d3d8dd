//! The `omis` command line: one binary, clap subcommands.

mod bench;
mod bench_coordinator;
mod bench_service;
mod bundle;
mod child_coordinator;
mod choices;
mod client;
mod compare;
mod diff;
mod healthcheck;
mod job_args;
mod job_cmds;
mod out_path;
mod pools;
mod procstat;
mod progress;
mod render;
mod service_cmds;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "omis",
    version,
    about = "Bidirectional path tracer with optimal MIS"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene to an EXR (and optionally a PNG preview), through an embedded coordinator
    /// and local worker processes (or --in-process).
    Render(render::RenderArgs),
    /// Run the coordinator: REST API, job store, task leases (and optionally local workers).
    Serve(service_cmds::ServeArgs),
    /// Run a worker that renders tasks for a coordinator.
    Worker(service_cmds::WorkerArgs),
    /// Submit a job to a coordinator (optionally wait for it and download the EXR).
    Submit(service_cmds::SubmitArgs),
    /// Write the bundle `submit` uploads for a scene file: the scene and every file it reads.
    Bundle(bundle::BundleArgs),
    /// A summary of the farm (jobs and workers by state, the queue), or of one job; --json
    /// for the raw document.
    Status(job_cmds::StatusArgs),
    /// List jobs as a table (--state, --name to filter; --json for the documents).
    Jobs(job_cmds::JobsArgs),
    /// Pause a job: it gets no new tasks; those in hand finish and are kept.
    Pause(job_cmds::JobArgs),
    /// Resume a paused job.
    Resume(job_cmds::JobArgs),
    /// Queue a failed job's failed tasks again (after a fix) and go on with it.
    Requeue(job_cmds::JobArgs),
    /// Submit a failed or cancelled job again as a new job; prints the new job's id.
    Retry(job_cmds::JobArgs),
    /// Delete a job that has ended, with every file it stored.
    Delete(job_cmds::JobArgs),
    /// Set a job's priority (higher first).
    Priority(job_cmds::PriorityArgs),
    /// Download a job's EXR (or preview, error map, convergence plot).
    Download(service_cmds::DownloadArgs),
    /// Cancel a job.
    Cancel(service_cmds::IdArgs),
    /// List the coordinator's workers, or disable, enable or drain one.
    Workers(pools::WorkersArgs),
    /// Show a job's task history: every attempt, failed ones first.
    Tasks(pools::TasksArgs),
    /// Compare an image with a reference: relMSE, MSE, optional error map.
    Diff(diff::DiffArgs),
    /// Measure BVH build time, ray rates and integrator throughput.
    Bench(bench::BenchArgs),
    /// Measure the render service: throughput with 1, 2, ... worker processes vs in-process,
    /// bytes shipped per sample, coordinator memory, pass latency.
    BenchService(bench_service::BenchServiceArgs),
    /// Load-test the coordinator alone: real task results recorded once, replayed from N
    /// simulated workers; results/s, MB/s, coordinator CPU per result, peak RSS, disk written,
    /// pass latency.
    BenchCoordinator(bench_coordinator::BenchCoordinatorArgs),
    /// Compare MIS strategies at equal spp (and equal time) against a reference: table and plots.
    Compare(compare::CompareArgs),
    /// Check that a coordinator answers /healthz (exit status 0 when healthy; for containers).
    Healthcheck(healthcheck::HealthcheckArgs),
}

/// Runs the command line; returns the process exit code. Errors are printed as one line.
pub fn main() -> i32 {
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        // Help and version go out whole (`omis` alone prints its help and exits 2); a usage
        // error is one line, like every other error.
        Err(e) if !e.use_stderr() => {
            let _ = e.print();
            return 0;
        }
        Err(e) if e.kind() == clap::error::ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => {
            let _ = e.print();
            return 2;
        }
        Err(e) => {
            // clap's first paragraph says what is wrong (and which argument); usage and tips
            // follow it.
            let text = e.render().to_string();
            let first: Vec<&str> = text
                .lines()
                .map(str::trim)
                .skip_while(|l| l.is_empty())
                .take_while(|l| !l.is_empty())
                .collect();
            let first = first.join(" ");
            let first = first.strip_prefix("error: ").unwrap_or(&first);
            eprintln!("omis: error: {first} (--help lists the options)");
            return 2;
        }
    };
    let result = match cli.command {
        Command::Render(a) => render::run(a),
        Command::Serve(a) => service_cmds::serve(a),
        Command::Worker(a) => service_cmds::worker(a),
        Command::Submit(a) => service_cmds::submit(a),
        Command::Bundle(a) => bundle::run(a),
        Command::Status(a) => job_cmds::status(a),
        Command::Jobs(a) => job_cmds::jobs(a),
        Command::Pause(a) => job_cmds::action(a, "pause"),
        Command::Resume(a) => job_cmds::action(a, "resume"),
        Command::Requeue(a) => job_cmds::action(a, "requeue"),
        Command::Retry(a) => job_cmds::action(a, "retry"),
        Command::Delete(a) => job_cmds::delete(a),
        Command::Priority(a) => job_cmds::priority(a),
        Command::Download(a) => service_cmds::download(a),
        Command::Cancel(a) => service_cmds::cancel(a),
        Command::Workers(a) => pools::workers(a),
        Command::Tasks(a) => pools::tasks(a),
        Command::Diff(a) => diff::run(a),
        Command::Bench(a) => bench::run(a),
        Command::BenchService(a) => bench_service::run(a),
        Command::BenchCoordinator(a) => bench_coordinator::run(a),
        Command::Compare(a) => compare::run(a),
        Command::Healthcheck(a) => healthcheck::run(a),
    };
    match result {
        Ok(()) => 0,
        Err(e) => {
            let msg = format!("{e:#}").replace('\n', " ");
            eprintln!("omis: error: {msg}");
            1
        }
    }
}

/// Parses "WxH".
pub(crate) fn parse_resolution(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("resolution '{s}' is not WxH"))?;
    let w: u32 = w
        .trim()
        .parse()
        .map_err(|_| format!("bad width in '{s}'"))?;
    let h: u32 = h
        .trim()
        .parse()
        .map_err(|_| format!("bad height in '{s}'"))?;
    if w == 0 || h == 0 || w > 16384 || h > 16384 {
        return Err(format!(
            "resolution '{s}' must be within 1x1 .. 16384x16384"
        ));
    }
    Ok((w, h))
}

/// A rayon pool with `threads` threads (0 = all cores).
pub(crate) fn thread_pool(threads: usize) -> anyhow::Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| anyhow::anyhow!("cannot start {threads} threads: {e}"))
}
