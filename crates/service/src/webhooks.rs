//! Webhooks: which URLs may receive deliveries (SSRF policy), how a delivery is signed,
//! and the dispatcher that sends the outbox (`store/webhooks.rs`) with retries.
//!
//! Why an outbox: the delivery row is written in the transaction that ends the job
//! (`jobs::queue`), so a crash between "job finished" and "told the customer" loses
//! nothing, and sending happens on a task of its own, never on a worker's time. Every
//! `serve` and `worker` process runs a dispatcher; a delivery is claimed with a lease,
//! as a job is, so two processes never send the same attempt.
//!
//! Why the address is checked at delivery too, and the connection pinned to it: a name
//! that resolved to a public address at registration may resolve to 127.0.0.1 later (DNS
//! rebinding); redirects are not followed for the same reason.

use crate::jobs::acceptance::judge;
use crate::jobs::queue::Queue;
use crate::store::webhooks::DeliveryRow;
use crate::store::{now_ms, rfc3339, Store};
use hmac::{Hmac, KeyInit, Mac};
use serde_json::json;
use std::net::{IpAddr, SocketAddr};
use std::time::Duration;
use tokio::sync::watch;

/// The event types a webhook can subscribe to: `job.finished` on every end, the others
/// on that end only.
pub const EVENTS: [&str; 5] = [
    "job.finished",
    "job.succeeded",
    "job.degraded",
    "job.failed",
    "job.cancelled",
];

/// Where deliveries may go, and how they are retried.
#[derive(Clone, Debug)]
pub struct WebhookConfig {
    /// Deliver to loopback, private and link-local addresses too (`--allow-private-webhooks`).
    pub allow_private: bool,
    /// Attempts before a delivery is given up (`failed`).
    pub max_attempts: i64,
    /// First retry delay, doubled per attempt up to [`MAX_BACKOFF`].
    pub backoff: Duration,
    /// One attempt's limit (connect + answer).
    pub timeout: Duration,
    /// How often an idle dispatcher looks for due deliveries.
    pub poll: Duration,
}

impl Default for WebhookConfig {
    fn default() -> Self {
        Self {
            allow_private: false,
            max_attempts: 8,
            backoff: Duration::from_secs(1),
            timeout: Duration::from_secs(10),
            poll: Duration::from_millis(250),
        }
    }
}

/// The longest wait between two attempts.
pub const MAX_BACKOFF: Duration = Duration::from_secs(3600);

/// An address a webhook must not reach without `--allow-private-webhooks`: loopback,
/// private (RFC 1918, ULA), link-local (cloud metadata at 169.254.169.254), CGNAT,
/// unspecified, multicast, broadcast, documentation ranges, and IPv4 mapped into IPv6.
pub fn is_private(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(a) => {
            let o = a.octets();
            a.is_loopback()
                || a.is_private()
                || a.is_link_local()
                || a.is_unspecified()
                || a.is_multicast()
                || a.is_broadcast()
                || a.is_documentation()
                || o[0] == 0
                || (o[0] == 100 && (64..128).contains(&o[1]))
                || o[0] >= 240
        }
        IpAddr::V6(a) => {
            if let Some(v4) = a.to_ipv4_mapped() {
                return is_private(IpAddr::V4(v4));
            }
            let s = a.segments();
            a.is_loopback()
                || a.is_unspecified()
                || a.is_multicast()
                || (s[0] & 0xfe00) == 0xfc00
                || (s[0] & 0xffc0) == 0xfe80
                || (s[0] == 0x2001 && s[1] == 0x0db8)
        }
    }
}

/// A webhook URL, checked: `http` or `https`, a host, no credentials, at most 2048
/// bytes; `Err` says what was expected.
pub fn parse_url(text: &str) -> Result<url::Url, String> {
    if text.len() > 2048 {
        return Err(format!("a URL of at most 2048 bytes, got {}", text.len()));
    }
    let u = url::Url::parse(text).map_err(|e| format!("an http or https URL, got {e}"))?;
    if !matches!(u.scheme(), "http" | "https") {
        return Err(format!("an http or https URL, got scheme {}", u.scheme()));
    }
    if u.host_str().is_none_or(str::is_empty) {
        return Err("an http or https URL with a host".into());
    }
    if !u.username().is_empty() || u.password().is_some() {
        return Err("a URL without credentials (the signature authenticates rigcal; give the receiver's secret as the webhook's secret)".into());
    }
    Ok(u)
}

/// Resolve the URL's host and check every address against the policy; the addresses to
/// connect to. `Err` names the refused address.
pub async fn resolve(u: &url::Url, allow_private: bool) -> Result<Vec<SocketAddr>, String> {
    let host = u.host_str().unwrap_or_default();
    let port = u.port_or_known_default().unwrap_or(80);
    let bare = host.trim_start_matches('[').trim_end_matches(']');
    let addrs: Vec<SocketAddr> = match bare.parse::<IpAddr>() {
        Ok(ip) => vec![SocketAddr::new(ip, port)],
        // Bounded: a resolver that never answers must not hold the request.
        Err(_) => tokio::time::timeout(
            Duration::from_secs(5),
            tokio::net::lookup_host((bare, port)),
        )
        .await
        .map_err(|_| format!("a host that resolves within 5 s, got {host}"))?
        .map_err(|e| format!("a host that resolves, got {host}: {e}"))?
        .collect(),
    };
    if addrs.is_empty() {
        return Err(format!("a host that resolves, got {host}: no address"));
    }
    if !allow_private {
        if let Some(a) = addrs.iter().find(|a| is_private(a.ip())) {
            return Err(format!(
                "a URL whose host resolves to public addresses only, got {host} → {} (loopback, private and link-local addresses are refused unless the server runs with --allow-private-webhooks)",
                a.ip()
            ));
        }
    }
    Ok(addrs)
}

/// `Rigcal-Signature` of `body` sent at `t` (Unix seconds): `t=T,v1=HEX` where HEX is the
/// HMAC-SHA256 of `"T.BODY"` keyed by the webhook's secret, as Stripe signs. A receiver
/// recomputes it and refuses a `t` older than a few minutes (replays).
pub fn signature(secret: &str, t: i64, body: &str) -> String {
    // HMAC takes a key of any length: `new_from_slice` cannot fail for it.
    let mut mac = <Hmac<sha2::Sha256> as KeyInit>::new_from_slice(secret.as_bytes())
        .expect("HMAC accepts keys of every length");
    mac.update(format!("{t}.").as_bytes());
    mac.update(body.as_bytes());
    format!("t={t},v1={}", hex::encode(mac.finalize().into_bytes()))
}

/// The wait before attempt `attempts + 1` after `attempts` failed ones.
pub fn backoff(cfg: &WebhookConfig, attempts: i64) -> Duration {
    let factor = 2u32.saturating_pow((attempts.max(1) - 1).min(30) as u32);
    cfg.backoff.saturating_mul(factor).min(MAX_BACKOFF)
}

/// Deliveries in flight at once per process: a receiver that hangs holds one slot for
/// its timeout, never the others.
pub const MAX_IN_FLIGHT: usize = 16;

/// Run a dispatcher until `stop` turns true. Deliveries run as tasks of their own (at
/// most [`MAX_IN_FLIGHT`]); one cut short by the process ending is sent again when its
/// lease expires — delivery is at least once, `Rigcal-Delivery` names it for dedupe.
pub fn spawn(
    store: Store,
    cfg: WebhookConfig,
    mut stop: watch::Receiver<bool>,
) -> tokio::task::JoinHandle<()> {
    let owner = format!("{}/{}", std::process::id(), uuid::Uuid::new_v4().simple());
    let slots = std::sync::Arc::new(tokio::sync::Semaphore::new(MAX_IN_FLIGHT));
    let lease_ms = 3 * cfg.timeout.as_millis() as i64 + 5000;
    tokio::spawn(async move {
        loop {
            if *stop.borrow() {
                return;
            }
            let Ok(slot) = slots.clone().acquire_owned().await else {
                return;
            };
            match store.claim_delivery(&owner, lease_ms).await {
                Ok(Some(d)) => {
                    let (store, cfg, owner) = (store.clone(), cfg.clone(), owner.clone());
                    tokio::spawn(async move {
                        if let Err(e) = deliver(&store, &cfg, &owner, d).await {
                            tracing::warn!(error = %e, "webhook delivery could not be recorded");
                        }
                        drop(slot);
                    });
                    continue;
                }
                Ok(None) => drop(slot),
                Err(e) => {
                    drop(slot);
                    tracing::warn!(error = %e, "claiming a webhook delivery");
                }
            }
            tokio::select! {
                _ = tokio::time::sleep(cfg.poll) => {}
                _ = stop.changed() => {}
            }
        }
    })
}

/// The body of a delivery: the event, the job as it ended, its acceptance verdict.
async fn body(store: &Store, d: &DeliveryRow) -> Result<String, String> {
    let queue = Queue::new(store.db.clone());
    let job = queue
        .get(&d.job_id)
        .await
        .map_err(|e| e.to_string())?
        .ok_or_else(|| format!("internal: job {} of the delivery is missing", d.job_id))?;
    let tenant = store
        .tenant(&job.tenant_id)
        .await
        .map_err(|e| e.to_string())?
        .ok_or_else(|| "internal: the job's tenant is missing".to_string())?;
    let model = match &job.vehicle_model {
        Some(m) => store
            .vehicle_model(&job.tenant_id, m)
            .await
            .map_err(|e| e.to_string())?
            .map(|r| r.document),
        None => None,
    };
    let acceptance = judge(&job, &tenant, model.as_ref());
    let v = json!({
        "id": d.id,
        "type": d.event,
        "created_at": rfc3339(d.created_at),
        "data": {"job": {
            "id": job.id,
            "session_id": job.session_id,
            "vehicle_id": job.vehicle_id,
            "vehicle_model": job.vehicle_model,
            "status": job.status,
            "error": job.error.as_deref().and_then(|e| serde_json::from_str::<serde_json::Value>(e).ok()),
            "residual_rms_px": job.residual_rms_px,
            "worst_sigma_translation_m": job.worst_sigma_translation_m,
            "worst_sigma_rotation_deg": job.worst_sigma_rotation_deg,
            "finished_at": job.finished_at.map(rfc3339),
            "acceptance": acceptance,
            "links": {
                "self": format!("/v1/jobs/{}", job.id),
                "result": format!("/v1/jobs/{}/result", job.id),
            },
        }},
    });
    serde_json::to_string(&v).map_err(|e| e.to_string())
}

/// One attempt of `d`, recorded; retried later or ended.
async fn deliver(
    store: &Store,
    cfg: &WebhookConfig,
    owner: &str,
    d: DeliveryRow,
) -> sqlx::Result<()> {
    let attempt = d.attempts + 1;
    let started = std::time::Instant::now();
    let body_text = match &d.body {
        Some(b) => Ok(b.clone()),
        None => body(store, &d).await,
    };
    let outcome: Result<u16, String> = match &body_text {
        Err(e) => Err(e.clone()),
        Ok(b) => send(cfg, &d, b).await,
    };
    let ms = started.elapsed().as_millis() as i64;
    let (status_code, error) = match &outcome {
        Ok(code) if (200..300).contains(code) => (Some(*code as i64), None),
        Ok(code) => (
            Some(*code as i64),
            Some(format!("the receiver answered {code}")),
        ),
        Err(e) => (None, Some(e.clone())),
    };
    let delivered = error.is_none();
    let next = if delivered || attempt >= cfg.max_attempts {
        None
    } else {
        Some(now_ms() + backoff(cfg, attempt).as_millis() as i64)
    };
    store
        .record_attempt(
            &d.id,
            owner,
            attempt,
            body_text.as_ref().ok().map(String::as_str),
            status_code,
            error.as_deref(),
            ms,
            delivered,
            next,
        )
        .await
}

/// POST `body` to the webhook's URL, connecting only to its checked addresses.
async fn send(cfg: &WebhookConfig, d: &DeliveryRow, body: &str) -> Result<u16, String> {
    let u = parse_url(&d.url).map_err(|e| format!("the stored URL: {e}"))?;
    let addrs = resolve(&u, cfg.allow_private).await?;
    let host = u.host_str().unwrap_or_default().to_string();
    let client = reqwest::Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .timeout(cfg.timeout)
        .resolve_to_addrs(&host, &addrs)
        .user_agent(concat!("rigcal-webhooks/", env!("CARGO_PKG_VERSION")))
        .build()
        .map_err(|e| format!("building the HTTP client: {e}"))?;
    let t = now_ms() / 1000;
    let resp = client
        .post(u)
        .header("content-type", "application/json")
        .header("rigcal-event", &d.event)
        .header("rigcal-delivery", &d.id)
        .header("rigcal-signature", signature(&d.secret, t, body))
        .body(body.to_string())
        .send()
        .await
        .map_err(|e| format!("sending: {e}"))?;
    Ok(resp.status().as_u16())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn private_addresses_are_recognised() {
        for a in [
            "127.0.0.1",
            "10.1.2.3",
            "172.16.0.1",
            "192.168.1.1",
            "169.254.169.254",
            "0.0.0.0",
            "100.64.0.1",
            "224.0.0.1",
            "255.255.255.255",
            "::1",
            "fe80::1",
            "fd00::1",
            "::ffff:127.0.0.1",
            "::",
        ] {
            assert!(is_private(a.parse().unwrap()), "{a}");
        }
        for a in ["93.184.216.34", "8.8.8.8", "2606:4700::1111", "172.32.0.1"] {
            assert!(!is_private(a.parse().unwrap()), "{a}");
        }
    }

    #[test]
    fn urls_are_checked() {
        assert!(parse_url("https://hooks.example.com/rigcal?x=1").is_ok());
        for bad in [
            "ftp://x/",
            "http://",
            "not a url",
            "http://user:pw@example.com/",
            "file:///etc/passwd",
        ] {
            assert!(parse_url(bad).is_err(), "{bad}");
        }
        assert!(parse_url(&format!("https://e.com/{}", "a".repeat(3000))).is_err());
    }

    #[tokio::test]
    async fn loopback_and_metadata_hosts_are_refused_unless_allowed() {
        for u in [
            "http://127.0.0.1:9/",
            "http://[::1]/",
            "http://169.254.169.254/latest/meta-data",
            "http://localhost:8080/",
        ] {
            let url = parse_url(u).unwrap();
            let e = resolve(&url, false).await.unwrap_err();
            assert!(e.contains("--allow-private-webhooks"), "{u}: {e}");
            assert!(resolve(&url, true).await.is_ok(), "{u}");
        }
        assert!(resolve(&parse_url("http://93.184.216.34/").unwrap(), false)
            .await
            .is_ok());
    }

    #[test]
    fn signature_is_the_hmac_of_time_and_body() {
        // Known answer: HMAC-SHA256(key "secret", "1700000000.{}"), computed with
        // Python's hmac module.
        assert_eq!(
            signature("secret", 1_700_000_000, "{}"),
            "t=1700000000,v1=b8569b78799ff9e3cbff0fc2d63a33a2b57f3282abd07c37ae5e8e7d79a5f163"
        );
    }

    #[test]
    fn backoff_doubles_up_to_an_hour() {
        let c = WebhookConfig::default();
        assert_eq!(backoff(&c, 1), Duration::from_secs(1));
        assert_eq!(backoff(&c, 2), Duration::from_secs(2));
        assert_eq!(backoff(&c, 4), Duration::from_secs(8));
        assert_eq!(backoff(&c, 40), MAX_BACKOFF);
    }
}
