//! Resource limits of the real server (issue 24): archives streamed in bounded memory,
//! archive uploads and event streams capped, connections and bodies timed out, and the
//! errors hyper raises itself answered as problem+json.

mod common;

use common::*;
use std::io::Write;
use std::time::Duration;

/// A zip of `entries` entries of `entry_bytes` zeros each (deflated once, copied raw:
/// megabytes on the wire, gigabytes unpacked). The first is named `first`.
fn zip_bomb(first: &str, entries: usize, entry_bytes: usize) -> Vec<u8> {
    let deflated = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .large_file(true);
    let mut one = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    one.start_file("x", deflated).unwrap();
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..entry_bytes >> 20 {
        one.write_all(&zeros).unwrap();
    }
    let mut src = one.finish_into_readable().unwrap();
    let mut out = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for i in 0..entries {
        let name = if i == 0 {
            first.to_string()
        } else {
            format!("pad/{i:04}.bin")
        };
        out.raw_copy_file_rename(src.by_name("x").unwrap(), name)
            .unwrap();
    }
    out.finish().unwrap().into_inner()
}

fn blobs_tmp_is_empty(dir: &std::path::Path) -> bool {
    std::fs::read_dir(dir.join("blobs").join("tmp"))
        .map(|mut d| d.next().is_none())
        .unwrap_or(true)
}

/// Finding 2: a 3 MB zip that unpacks to 3 GiB is refused (413, naming the limit) while
/// the server's peak memory grows by less than 64 MiB (it held 1 GiB before); a single
/// entry larger than the largest image is refused at that size, naming the entry, and so
/// is a `session.json` beyond the manifest limit; nothing is left in `blobs/tmp`.
#[tokio::test]
async fn zip_bombs_are_refused_in_bounded_memory() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    let post = |url: String, zip: Vec<u8>| {
        c.post(url)
            .header("content-type", "application/zip")
            .body(zip)
            .send()
    };
    let before = peak_rss(s.child.id());
    let bomb = zip_bomb("front/0000.png", 48, 64 << 20);
    assert!(bomb.len() < 8 << 20, "{} bytes", bomb.len());
    let r = post(s.url("/v1/sessions"), bomb).await.unwrap();
    let body = expect_problem(r, 413, "payload-too-large").await;
    assert!(
        body["detail"]
            .as_str()
            .unwrap()
            .contains("unpacks to more than"),
        "{body}"
    );

    let sess = create_session(&c, &s, &image_session(1, 64, 48)).await;
    let sid = sess["id"].as_str().unwrap();
    let archive = s.url(&format!("/v1/sessions/{sid}/archive"));
    let r = post(archive.clone(), zip_bomb("front/0000.png", 1, 100 << 20))
        .await
        .unwrap();
    let body = expect_problem(r, 413, "payload-too-large").await;
    let detail = body["detail"].as_str().unwrap();
    assert!(
        detail.contains("front/0000.png") && detail.contains("largest image"),
        "{body}"
    );
    let after = peak_rss(s.child.id());
    assert!(
        after < before + (64 << 20),
        "peak RSS {} MiB → {} MiB",
        before >> 20,
        after >> 20
    );

    // The manifest is parsed in memory, so it has its own (smaller) limit.
    let r = post(archive, zip_bomb("session.json", 1, 100 << 20))
        .await
        .unwrap();
    let body = expect_problem(r, 413, "payload-too-large").await;
    assert!(
        body["detail"].as_str().unwrap().contains("session.json"),
        "{body}"
    );
    assert!(blobs_tmp_is_empty(dir.path()));
    let view = get_json(&c, &s, &format!("/v1/sessions/{sid}")).await;
    assert_eq!(view["images_received"], 0, "{view}");
}

/// A tar streamed slowly holds its archive slot: with one slot, a second archive upload
/// meanwhile is 503 `busy` with `Retry-After`, and the first still succeeds.
#[tokio::test]
async fn concurrent_archive_uploads_are_capped() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(
        dir.path(),
        &["--workers", "0", "--max-concurrent-archives", "1"],
    );
    let c = client(&key);
    let sess = create_session(&c, &s, &image_session(1, 64, 48)).await;
    let sid = sess["id"].as_str().unwrap().to_string();
    let tar = tar_archive(&[("front/0000.png", png(64, 48, 1))]);
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut slow = tokio::net::TcpStream::connect(s.base.trim_start_matches("http://"))
        .await
        .unwrap();
    let head = format!(
        "POST /v1/sessions/{sid}/archive HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {key}\r\nContent-Type: application/x-tar\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        tar.len()
    );
    slow.write_all(head.as_bytes()).await.unwrap();
    slow.write_all(&tar[..512]).await.unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let r = c
        .post(s.url(&format!("/v1/sessions/{sid}/archive")))
        .header("content-type", "application/x-tar")
        .body(tar.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(
        r.headers()
            .get("retry-after")
            .map(|v| v.to_str().unwrap().to_string()),
        Some("5".to_string())
    );
    expect_problem(r, 503, "busy").await;
    slow.write_all(&tar[512..]).await.unwrap();
    let mut answer = Vec::new();
    slow.read_to_end(&mut answer).await.unwrap();
    let answer = String::from_utf8_lossy(&answer);
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
}

/// Finding 6: a connection that sends half its headers, or nothing after a response,
/// is closed after the header timeout; a body that stops is answered 408 after the
/// body timeout. Each is a flag.
#[tokio::test]
async fn idle_and_slow_connections_are_timed_out() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(
        dir.path(),
        &[
            "--workers",
            "0",
            "--header-timeout-seconds",
            "1",
            "--body-timeout-seconds",
            "1",
        ],
    );
    let addr = s.base.trim_start_matches("http://").to_string();
    let closed_within = |mut sock: tokio::net::TcpStream, secs: u64| async move {
        let mut buf = vec![0u8; 65536];
        tokio::time::timeout(Duration::from_secs(secs), async {
            loop {
                match sock.read(&mut buf).await {
                    Ok(0) | Err(_) => return,
                    Ok(_) => continue,
                }
            }
        })
        .await
        .is_ok()
    };
    // Half-sent headers.
    let mut sock = tokio::net::TcpStream::connect(&addr).await.unwrap();
    sock.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        .await
        .unwrap();
    assert!(closed_within(sock, 5).await, "half-sent headers kept open");
    // Idle keep-alive after a full exchange.
    let mut sock = tokio::net::TcpStream::connect(&addr).await.unwrap();
    sock.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .unwrap();
    assert!(closed_within(sock, 5).await, "idle keep-alive kept open");
    // A body that stops after 10 of 100 bytes.
    let sess = create_session(&client(&key), &s, &image_session(1, 64, 48)).await;
    let sid = sess["id"].as_str().unwrap();
    let head = format!(
        "PUT /v1/sessions/{sid}/images/front/0 HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {key}\r\nContent-Type: image/png\r\nContent-Length: 100\r\n\r\n0123456789"
    );
    let (status, head, body) = raw_request(&s, head.as_bytes()).await;
    assert_eq!(status, 408, "{head}");
    assert_eq!(body["type"], "urn:rigcal:problem:request-timeout", "{body}");
}

/// Finding 9: what hyper refuses before any handler runs is problem+json too.
#[tokio::test]
async fn http_layer_errors_are_problem_json() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let many: String = (0..150).map(|i| format!("X-H{i}: v\r\n")).collect();
    let cases = [
        (format!("GET /healthz HTTP/1.1\r\nHost: x\r\n{many}\r\n"), 431),
        (
            format!("GET /{} HTTP/1.1\r\nHost: x\r\n\r\n", "a".repeat(70_000)),
            414,
        ),
        (
            "POST /v1/sessions HTTP/1.1\r\nHost: x\r\nContent-Length: 99999999999999999999999\r\n\r\n"
                .to_string(),
            400,
        ),
        ("GARBAGE\r\n\r\n".to_string(), 400),
    ];
    for (request, want) in cases {
        let (status, head, body) = raw_request(&s, request.as_bytes()).await;
        assert_eq!(status, want, "{head}");
        assert!(
            head.to_ascii_lowercase()
                .contains("content-type: application/problem+json"),
            "{head}"
        );
        assert_eq!(body["status"], want, "{body}");
    }
    // The server still answers normally.
    let (status, _, _) = raw_request(
        &s,
        b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
    )
    .await;
    assert_eq!(status, 200);
}

/// Finding 10: event streams per tenant are capped (429 naming the cap); closing one
/// frees its slot; another tenant is not affected.
#[tokio::test]
async fn event_streams_are_capped_per_tenant() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let other = api_key(dir.path(), "globex");
    let s = Server::start(
        dir.path(),
        &["--workers", "0", "--max-streams-per-tenant", "2"],
    );
    let c = client(&key);
    let open = |c: reqwest::Client| {
        let url = s.url("/v1/events");
        async move { c.get(url).send().await.unwrap() }
    };
    let a = open(c.clone()).await;
    let b = open(c.clone()).await;
    assert_eq!((a.status().as_u16(), b.status().as_u16()), (200, 200));
    let third = open(c.clone()).await;
    let body = expect_problem(third, 429, "too-many-streams").await;
    assert!(
        body["detail"].as_str().unwrap().contains("at most 2"),
        "{body}"
    );
    let theirs = open(client(&other)).await;
    assert_eq!(theirs.status().as_u16(), 200);
    drop(a);
    // The server notices the closed stream at its next write (the keep-alive comment
    // or an event); poll until the slot is free.
    let mut freed = false;
    for _ in 0..40 {
        tokio::time::sleep(Duration::from_millis(500)).await;
        let r = open(c.clone()).await;
        if r.status().as_u16() == 200 {
            freed = true;
            break;
        }
    }
    assert!(freed, "the closed stream's slot was never given back");
    drop(b);
}
