//! In-process metrics, exposed in the Prometheus text format at `/metrics`.
//!
//! Counters and fixed-bucket histograms behind one mutex: a scrape or an update is a
//! few hundred nanoseconds, far below anything a request or a job stage costs.
//! Queue depth and jobs by state are read from the database at scrape time, so they are
//! right even when the workers run in other processes.

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::Mutex;

const LATENCY_BUCKETS: [f64; 12] = [
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0,
];
const STAGE_BUCKETS: [f64; 10] = [0.01, 0.05, 0.1, 0.5, 1.0, 5.0, 10.0, 60.0, 300.0, 1800.0];

#[derive(Clone, Debug, Default)]
struct Histogram {
    counts: Vec<u64>,
    sum: f64,
    count: u64,
}

impl Histogram {
    fn observe(&mut self, buckets: &[f64], x: f64) {
        if self.counts.is_empty() {
            self.counts = vec![0; buckets.len()];
        }
        for (i, b) in buckets.iter().enumerate() {
            if x <= *b {
                self.counts[i] += 1;
            }
        }
        self.sum += x;
        self.count += 1;
    }

    fn render(&self, out: &mut String, name: &str, labels: &str, buckets: &[f64]) {
        let sep = if labels.is_empty() { "" } else { "," };
        for (i, b) in buckets.iter().enumerate() {
            let c = self.counts.get(i).copied().unwrap_or(0);
            let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"{b}\"}} {c}");
        }
        let _ = writeln!(
            out,
            "{name}_bucket{{{labels}{sep}le=\"+Inf\"}} {}",
            self.count
        );
        let _ = writeln!(out, "{name}_sum{{{labels}}} {}", self.sum);
        let _ = writeln!(out, "{name}_count{{{labels}}} {}", self.count);
    }
}

#[derive(Default)]
struct Inner {
    requests: BTreeMap<(String, String, u16), Histogram>,
    stages: BTreeMap<String, Histogram>,
    jobs_finished: BTreeMap<String, u64>,
}

#[derive(Default)]
pub struct Metrics {
    inner: Mutex<Inner>,
}

fn escape(s: &str) -> String {
    s.replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n")
}

impl Metrics {
    pub fn request(&self, method: &str, route: &str, status: u16, seconds: f64) {
        if let Ok(mut m) = self.inner.lock() {
            m.requests
                .entry((method.to_string(), route.to_string(), status))
                .or_default()
                .observe(&LATENCY_BUCKETS, seconds);
        }
    }

    pub fn stage(&self, stage: &str, seconds: f64) {
        if let Ok(mut m) = self.inner.lock() {
            m.stages
                .entry(stage.to_string())
                .or_default()
                .observe(&STAGE_BUCKETS, seconds);
        }
    }

    pub fn job_finished(&self, status: &str) {
        if let Ok(mut m) = self.inner.lock() {
            *m.jobs_finished.entry(status.to_string()).or_default() += 1;
        }
    }

    /// Render everything, with `jobs_by_status` from the database (every status, zeros
    /// included: a gauge that disappears reads as "no data", not as 0).
    pub fn render(&self, jobs_by_status: &[(String, i64)]) -> String {
        let mut out = String::new();
        out.push_str(
            "# HELP rigcal_queue_depth Jobs waiting to run.\n# TYPE rigcal_queue_depth gauge\n",
        );
        let queued = jobs_by_status
            .iter()
            .find(|(s, _)| s == "queued")
            .map_or(0, |(_, n)| *n);
        let _ = writeln!(out, "rigcal_queue_depth {queued}");
        out.push_str(
            "# HELP rigcal_jobs Jobs in the database by status.\n# TYPE rigcal_jobs gauge\n",
        );
        for (s, n) in jobs_by_status {
            let _ = writeln!(out, "rigcal_jobs{{status=\"{s}\"}} {n}");
        }
        let Ok(m) = self.inner.lock() else {
            return out;
        };
        out.push_str("# HELP rigcal_jobs_finished_total Jobs finished by this process's workers.\n# TYPE rigcal_jobs_finished_total counter\n");
        for (s, n) in &m.jobs_finished {
            let _ = writeln!(
                out,
                "rigcal_jobs_finished_total{{status=\"{}\"}} {n}",
                escape(s)
            );
        }
        out.push_str("# HELP rigcal_stage_duration_seconds Duration of pipeline stages.\n# TYPE rigcal_stage_duration_seconds histogram\n");
        for (stage, h) in &m.stages {
            h.render(
                &mut out,
                "rigcal_stage_duration_seconds",
                &format!("stage=\"{}\"", escape(stage)),
                &STAGE_BUCKETS,
            );
        }
        out.push_str("# HELP rigcal_http_request_duration_seconds HTTP request latency.\n# TYPE rigcal_http_request_duration_seconds histogram\n");
        for ((method, route, status), h) in &m.requests {
            h.render(
                &mut out,
                "rigcal_http_request_duration_seconds",
                &format!(
                    "method=\"{}\",route=\"{}\",status=\"{status}\"",
                    escape(method),
                    escape(route)
                ),
                &LATENCY_BUCKETS,
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_cumulative_buckets() {
        let m = Metrics::default();
        m.request("GET", "/v1/jobs/{id}", 200, 0.003);
        m.request("GET", "/v1/jobs/{id}", 200, 0.2);
        m.stage("trajectories", 0.7);
        let text = m.render(&[("queued".into(), 3), ("running".into(), 0)]);
        assert!(text.contains("rigcal_queue_depth 3"));
        assert!(text.contains("rigcal_jobs{status=\"running\"} 0"));
        assert!(text.contains(
            "rigcal_http_request_duration_seconds_bucket{method=\"GET\",route=\"/v1/jobs/{id}\",status=\"200\",le=\"0.005\"} 1"
        ));
        assert!(text.contains(
            "rigcal_http_request_duration_seconds_bucket{method=\"GET\",route=\"/v1/jobs/{id}\",status=\"200\",le=\"+Inf\"} 2"
        ));
        assert!(text.contains("rigcal_stage_duration_seconds_count{stage=\"trajectories\"} 1"));
    }
}
