//! The router, the `protocol` enums and proto/openapi.yaml agree.

use crate::common::repo;
use crate::common::service::{http, serve};
use crate::support::folder;
use serde_json::{Value, json};
use std::time::Duration;

/// (method, path) pairs of proto/openapi.yaml's `paths` (2-space YAML indentation).
fn openapi_routes() -> std::collections::BTreeSet<(String, String)> {
    let text = std::fs::read_to_string(repo().join("proto/openapi.yaml")).expect("openapi.yaml");
    let mut set = std::collections::BTreeSet::new();
    let mut in_paths = false;
    let mut path = String::new();
    for line in text.lines() {
        if !line.starts_with(' ') && !line.trim().is_empty() {
            in_paths = line.trim_end() == "paths:";
            continue;
        }
        if !in_paths {
            continue;
        }
        let indent = line.len() - line.trim_start().len();
        let key = line.trim().trim_end_matches(':');
        if indent == 2 && key.starts_with('/') {
            path = key.trim_matches(|c| c == '"' || c == '\'').to_string();
        } else if indent == 4 && ["get", "post", "put", "delete", "patch"].contains(&key) {
            set.insert((key.to_string(), path.clone()));
        }
    }
    set
}

#[test]
fn the_router_and_the_openapi_contract_have_the_same_routes() {
    let served: std::collections::BTreeSet<(String, String)> = omis::service::api::ROUTES
        .iter()
        .map(|(m, p)| (m.to_string(), p.to_string()))
        .collect();
    assert_eq!(openapi_routes(), served);
    // Every listed route is really served (the fallback answers 404 with field "path").
    let dir = folder("routes");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    for (m, p) in omis::service::api::ROUTES {
        let u = format!("{url}{}", p.replace("{id}", "0").replace("{worker}", "0"));
        let r = match *m {
            "get" => c.get(&u),
            "post" => c.post(&u),
            "put" => c.put(&u),
            "patch" => c.patch(&u),
            "delete" => c.delete(&u),
            _ => unreachable!(),
        }
        .timeout(Duration::from_secs(10))
        .send()
        .unwrap_or_else(|e| panic!("{m} {p}: the request itself failed: {e}"));
        let v: Value = r.json().unwrap_or(Value::Null);
        assert_ne!(v["field"], "path", "{m} {p} is not served");
    }
    // And a path outside the list is not.
    let v: Value = c
        .get(format!("{url}/v1/nothing"))
        .send()
        .expect("GET")
        .json()
        .expect("JSON");
    assert_eq!(v["field"], "path");
}

/// The `enum:` list of the schema `name` in proto/openapi.yaml's components (a schema of the
/// form `    Name:` / `      type: string` / `      enum: [a, b, c]`).
fn openapi_enum(name: &str) -> Vec<String> {
    let text = std::fs::read_to_string(repo().join("proto/openapi.yaml")).expect("openapi.yaml");
    let mut lines = text.lines().skip_while(|l| *l != "  schemas:");
    let header = format!("    {name}:");
    assert!(
        lines.any(|l| l == header),
        "no schema {name} in components.schemas"
    );
    for line in lines {
        let indent = line.len() - line.trim_start().len();
        if !line.trim().is_empty() && indent <= 4 {
            break;
        }
        if let Some(list) = line.strip_prefix("      enum: [") {
            let list = list.trim_end().strip_suffix(']').expect("a one-line enum");
            return list.split(',').map(|v| v.trim().to_string()).collect();
        }
    }
    panic!("schema {name} has no one-line enum");
}

#[test]
fn the_protocol_enums_are_the_openapi_enums() {
    use omis::protocol::{
        AttemptOutcome, EventKind, JobState, TaskKind, TaskState, WorkerAdmin, WorkerState,
    };
    fn names<T: serde::Serialize>(all: &[T], as_str: impl Fn(&T) -> &'static str) -> Vec<String> {
        all.iter()
            .map(|v| {
                // The wire name is the SQL name.
                assert_eq!(serde_json::to_value(v).expect("serialises"), as_str(v));
                as_str(v).to_string()
            })
            .collect()
    }
    assert_eq!(
        openapi_enum("JobState"),
        names(JobState::ALL, |s| s.as_str())
    );
    assert_eq!(
        openapi_enum("TaskState"),
        names(TaskState::ALL, |s| s.as_str())
    );
    assert_eq!(
        openapi_enum("TaskKind"),
        names(TaskKind::ALL, |s| s.as_str())
    );
    assert_eq!(
        openapi_enum("WorkerState"),
        names(WorkerState::ALL, |s| s.as_str())
    );
    assert_eq!(
        openapi_enum("EventKind"),
        names(EventKind::ALL, |s| s.as_str())
    );
    assert_eq!(
        openapi_enum("WorkerAdmin"),
        names(WorkerAdmin::ALL, |s| s.as_str())
    );
    assert_eq!(
        openapi_enum("AttemptOutcome"),
        names(AttemptOutcome::ALL, |s| s.as_str())
    );
}

#[test]
fn protocol_names_and_events_round_trip() {
    use omis::protocol::{
        CancelledEvent, EventKind, JobEvent, JobState, PassDoneEvent, TaskState, WorkerState,
    };
    for s in JobState::ALL {
        assert_eq!(s.as_str().parse::<JobState>(), Ok(*s));
    }
    for k in EventKind::ALL {
        assert_eq!(k.as_str().parse::<EventKind>(), Ok(*k));
    }
    for s in TaskState::ALL {
        assert_eq!(s.as_str().parse::<TaskState>(), Ok(*s));
    }
    for s in WorkerState::ALL {
        assert_eq!(s.as_str().parse::<WorkerState>(), Ok(*s));
    }
    assert!("Queued".parse::<JobState>().is_err());
    let e = JobEvent::PassDone(PassDoneEvent {
        pass: 2,
        spp: 12,
        seconds: 1.5,
        relmse: None,
    });
    // The SSE data carries the job and the time besides the event's fields.
    let mut data = e.data();
    data["job"] = "j".into();
    data["at"] = 3.0.into();
    assert_eq!(JobEvent::parse(e.kind(), data).expect("parses"), e);
    let c = JobEvent::Cancelled(CancelledEvent {});
    assert_eq!(c.data(), json!({}));
    assert!(c.kind().is_terminal() && !EventKind::TileDone.is_terminal());
}
