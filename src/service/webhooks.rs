//! Webhooks: a job's final event (`done`, `failed`, `cancelled`) POSTed as JSON to each
//! receiver, the coordinator's own (`omis serve --webhook`) and the job's
//! (`JobRequest::webhooks`). The store queues a delivery row in the transaction that ends the
//! job (`JobStore::set_job_state`), so a delivery survives a kill; `dispatch` makes the
//! attempts: at least once, each with the same delivery id (a receiver dedupes on it), retried
//! with exponential backoff until a 2xx answer or `MAX_ATTEMPTS`.

use super::App;
use super::store::{self, DeliveryAttempt, DeliveryRow, WebhookTarget};
use crate::protocol::{JobLinks, JobState, WebhookBody, WebhookJob, WebhookSpec};
use hmac::{Hmac, Mac};
use sha2::Sha256;
use std::collections::HashSet;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Attempts of a delivery before it counts as failed.
pub(crate) const MAX_ATTEMPTS: u32 = 8;
/// How long one attempt waits for the receiver's answer.
const ATTEMPT_TIMEOUT: Duration = Duration::from_secs(5);
/// The longest wait between two attempts, in seconds.
const MAX_BACKOFF_S: f64 = 300.0;
/// Receivers of one job at most.
pub(crate) const MAX_JOB_WEBHOOKS: usize = 8;
/// Longest receiver URL.
const MAX_URL: usize = 2048;
/// Longest secret.
const MAX_SECRET: usize = 256;
/// Deliveries started per look at the outbox.
const BATCH: u32 = 32;

/// Whether `url` can receive webhooks: an absolute `http://` URL with a host, at most
/// `MAX_URL` bytes. The error says what is wrong.
pub(crate) fn check_url(url: &str) -> Result<(), String> {
    if url.len() > MAX_URL {
        return Err(format!("at most {MAX_URL} bytes"));
    }
    let u = reqwest::Url::parse(url).map_err(|e| format!("not a URL: {e}"))?;
    match u.scheme() {
        "http" => {}
        "https" => {
            return Err(
                "https receivers are not supported by this coordinator (it is built \
                        without TLS); use an http:// receiver, e.g. a relay on the same network"
                    .into(),
            );
        }
        s => return Err(format!("scheme '{s}': an http:// URL is needed")),
    }
    if u.host_str().is_none_or(str::is_empty) {
        return Err("the URL has no host".into());
    }
    Ok(())
}

/// Checks a secret: 1 to `MAX_SECRET` bytes.
pub(crate) fn check_secret(secret: &str) -> Result<(), String> {
    if secret.is_empty() || secret.len() > MAX_SECRET {
        return Err(format!("1 to {MAX_SECRET} bytes"));
    }
    Ok(())
}

/// A job's receivers checked, as stored (JSON; None: it has none). The error names the field.
pub(crate) fn job_targets(hooks: &[WebhookSpec]) -> Result<Option<String>, (String, String)> {
    if hooks.is_empty() {
        return Ok(None);
    }
    if hooks.len() > MAX_JOB_WEBHOOKS {
        return Err((
            "webhooks".into(),
            format!("at most {MAX_JOB_WEBHOOKS} receivers per job"),
        ));
    }
    let mut targets = Vec::with_capacity(hooks.len());
    for (i, h) in hooks.iter().enumerate() {
        check_url(&h.url).map_err(|e| (format!("webhooks[{i}].url"), e))?;
        if let Some(s) = &h.secret {
            check_secret(s).map_err(|e| (format!("webhooks[{i}].secret"), e))?;
        }
        targets.push(WebhookTarget {
            url: h.url.clone(),
            secret: h.secret.clone(),
        });
    }
    serde_json::to_string(&targets)
        .map(Some)
        .map_err(|e| ("webhooks".into(), e.to_string()))
}

/// The URLs of a job's own receivers (stored JSON), for its status.
pub(crate) fn job_urls(stored: Option<&str>) -> Vec<String> {
    stored
        .and_then(|s| serde_json::from_str::<Vec<WebhookTarget>>(s).ok())
        .map(|t| t.into_iter().map(|t| t.url).collect())
        .unwrap_or_default()
}

/// `sha256=<hex HMAC-SHA256(secret, body)>`, the `X-Omis-Signature` header.
pub(crate) fn signature(secret: &str, body: &[u8]) -> String {
    // HMAC takes a key of any length.
    let mut mac = <Hmac<Sha256> as Mac>::new_from_slice(secret.as_bytes())
        .unwrap_or_else(|_| unreachable!("HMAC accepts every key length"));
    mac.update(body);
    let tag = mac.finalize().into_bytes();
    let hex: String = tag.iter().map(|b| format!("{b:02x}")).collect();
    format!("sha256={hex}")
}

/// Seconds to wait after failed attempt `n` (1-based): 1, 2, 4, ... at most `MAX_BACKOFF_S`.
fn backoff_s(n: u32) -> f64 {
    2f64.powi(n.saturating_sub(1).min(30) as i32)
        .min(MAX_BACKOFF_S)
}

/// The body of delivery `d`: the event and its job as it ended.
fn body_of(app: &App, d: &DeliveryRow) -> store::StoreResult<WebhookBody> {
    let db = app.db();
    let state = d.event.parse::<JobState>().unwrap_or(JobState::Failed);
    let job = match db.job(&d.job_id)? {
        Some(j) => WebhookJob {
            relmse: db.series(&j.id)?.last().and_then(|p| p.relmse),
            id: j.id.clone(),
            name: j.name,
            state: j.state,
            error: j.error,
            owner: j.owner,
            spp_done: j.spp_done,
            links: JobLinks::of(&j.id),
        },
        None => WebhookJob {
            id: d.job_id.clone(),
            name: None,
            state,
            error: None,
            owner: None,
            spp_done: 0,
            relmse: None,
            links: JobLinks::of(&d.job_id),
        },
    };
    Ok(WebhookBody {
        event: d.event.clone(),
        delivery_id: d.id.clone(),
        job,
        at: d.at,
    })
}

/// One attempt of delivery `d`; what it came to.
async fn attempt(app: &App, client: &reqwest::Client, d: &DeliveryRow) -> DeliveryAttempt {
    let n = d.attempts + 1;
    let retry_at = (n < MAX_ATTEMPTS).then(|| store::now() + backoff_s(n));
    let failed = |status: Option<u16>, error: String| DeliveryAttempt {
        status,
        error: Some(error),
        retry_at,
    };
    let body = match body_of(app, d)
        .and_then(|b| serde_json::to_vec(&b).map_err(|e| store::StoreError::new(e.to_string())))
    {
        Ok(b) => b,
        Err(e) => return failed(None, format!("cannot make the body: {e}")),
    };
    let mut req = client
        .post(&d.url)
        .header(reqwest::header::CONTENT_TYPE, "application/json")
        .header("X-Omis-Event", &d.event)
        .header("X-Omis-Delivery", &d.id);
    if let Some(secret) = &d.secret {
        req = req.header("X-Omis-Signature", signature(secret, &body));
    }
    match req.body(body).send().await {
        Ok(r) if r.status().is_success() => DeliveryAttempt {
            status: Some(r.status().as_u16()),
            error: None,
            retry_at: None,
        },
        Ok(r) => failed(
            Some(r.status().as_u16()),
            format!("the receiver answered {}", r.status()),
        ),
        Err(e) => failed(None, format!("no answer: {e}")),
    }
}

/// Makes the attempts of every pending delivery when due, several receivers at once, until the
/// coordinator stops; woken by `App::deliveries` when a job ends, else it looks every second.
pub(crate) async fn dispatch(app: Arc<App>) {
    let client = match reqwest::Client::builder()
        .timeout(ATTEMPT_TIMEOUT)
        .redirect(reqwest::redirect::Policy::none())
        .user_agent(concat!("omis/", env!("CARGO_PKG_VERSION")))
        .build()
    {
        Ok(c) => c,
        Err(e) => {
            tracing::error!("webhooks: cannot make the HTTP client: {e}; none is delivered");
            return;
        }
    };
    let in_flight: Arc<Mutex<HashSet<String>>> = Arc::default();
    while !app.stopping.load(Ordering::Relaxed) {
        let due = app.db().due_deliveries(store::now(), BATCH);
        match due {
            Ok(due) => {
                for d in due {
                    if !in_flight
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .insert(d.id.clone())
                    {
                        continue;
                    }
                    let (app, client, in_flight) = (app.clone(), client.clone(), in_flight.clone());
                    tokio::spawn(async move {
                        let outcome = attempt(&app, &client, &d).await;
                        if let Some(e) = &outcome.error {
                            let next = match outcome.retry_at {
                                Some(_) => "retrying",
                                None => "giving up",
                            };
                            tracing::warn!(
                                "webhook {} of job {} to {} (attempt {}): {e}; {next}",
                                d.id,
                                d.job_id,
                                d.url,
                                d.attempts + 1
                            );
                        }
                        if let Err(e) = app.db().record_delivery(&d.id, &outcome) {
                            tracing::error!("webhook {}: cannot record its attempt: {e}", d.id);
                        }
                        in_flight
                            .lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .remove(&d.id);
                        app.deliveries.notify_one();
                    });
                }
            }
            Err(e) => tracing::error!("webhooks: cannot read the outbox: {e}"),
        }
        let next = app.db().next_delivery_at().ok().flatten();
        let wait = next.map_or(1.0, |t| (t - store::now()).clamp(0.1, 1.0));
        tokio::select! {
            _ = app.deliveries.notified() => {}
            _ = tokio::time::sleep(Duration::from_secs_f64(wait)) => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signatures_and_urls() {
        // RFC 4231, test case 2.
        assert_eq!(
            signature("Jefe", b"what do ya want for nothing?"),
            "sha256=5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
        assert!(check_url("http://127.0.0.1:8080/hook").is_ok());
        for bad in ["ftp://x/y", "https://example.com/", "/relative", "http://"] {
            assert!(check_url(bad).is_err(), "{bad}");
        }
        assert_eq!(
            (1..=10).map(backoff_s).collect::<Vec<_>>(),
            [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 300.0]
        );
    }
}
