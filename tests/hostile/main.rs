//! Hostile input and faults against a real coordinator on 127.0.0.1: deep and extreme scene
//! files, slow and idle connections, uploads that claim more than they weigh, tasks that kill or
//! fail on their workers, a damaged database, a full disk, references full of NaN, and bodies
//! and tokens that bend the contract. Each ends with a clear error, the coordinator serving, and
//! nothing it had accepted lost.

#[path = "../common/mod.rs"]
mod common;
mod http;
mod scenes;
mod storage;
mod support;
mod uploads;
mod workers;
