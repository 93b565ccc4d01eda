//! The blob store as replicas share it (a local directory, or S3 in the remote run of
//! scripts/test.sh): two stores opened on the same location storing the same bytes at
//! once both succeed and store them once; what one stores the other reads, verified;
//! a hash that was never stored is absent, not an error.

mod common;

use common::*;
use rigcal_service::store::blob::sha256_hex;

#[tokio::test(flavor = "multi_thread")]
async fn two_replicas_storing_the_same_image_store_it_once() {
    let dir = tempfile::tempdir().unwrap();
    let (one, two) = (
        open_store(dir.path()).await.blobs,
        open_store(dir.path()).await.blobs,
    );
    let bytes: Vec<u8> = (0..200_000u32).map(|i| (i * 7 % 251) as u8).collect();
    let expected = sha256_hex(&bytes);
    assert!(!one.contains(&expected).await.unwrap());

    let racers: Vec<_> = (0..8)
        .map(|k| {
            let store = if k % 2 == 0 { one.clone() } else { two.clone() };
            let bytes = bytes.clone();
            tokio::task::spawn_blocking(move || store.put(&bytes))
        })
        .collect();
    for r in racers {
        assert_eq!(r.await.unwrap().unwrap(), expected);
    }
    assert!(two.contains(&expected).await.unwrap());
    let read = tokio::task::spawn_blocking(move || two.get(&expected))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(read, bytes);

    let never = sha256_hex(b"never stored");
    assert!(!one.contains(&never).await.unwrap());
    let err = tokio::task::spawn_blocking(move || one.get(&never))
        .await
        .unwrap()
        .unwrap_err();
    assert_eq!(err.kind(), std::io::ErrorKind::NotFound, "{err}");
}
