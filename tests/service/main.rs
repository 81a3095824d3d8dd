//! The render service with real processes on 127.0.0.1: a coordinator (`omis serve`), worker
//! processes, HTTP + SSE. Every image the service produces must equal the in-process render of
//! the same job (the tiling-invariance property across processes), whatever dies on the way.
//! Every process a test starts is killed when the test ends, also when it fails.

mod access;
mod bad_input;
mod checkpoints;
mod cli;
#[path = "../common/mod.rs"]
mod common;
mod contract;
mod controls;
mod jobs;
mod leases;
mod limits;
mod pool;
mod sequences;
mod support;
mod synthetic_stream;
mod time_budget;
mod webhooks;
mod worker_pools;
