//! The deployment files, checked without Docker (none runs here): compose.yaml parses,
//! every dependency names a service that can satisfy its condition, every rigcal
//! command line is one this build accepts, the URLs parse and point at the compose
//! services, and the Dockerfile copies only what exists and runs `rigcal` in both roles.

use rigcal_service::store::blob::BlobUrl;
use rigcal_service::store::db::DatabaseUrl;
use serde_norway::Value;
use std::path::Path;

const BIN: &str = env!("CARGO_BIN_EXE_rigcal");

fn compose() -> Value {
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("compose.yaml"))
        .expect("compose.yaml at the top level");
    let mut v: Value = serde_norway::from_str(&text).expect("compose.yaml is YAML");
    v.apply_merge().expect("merge keys resolve");
    v
}

fn str_list(v: &Value) -> Vec<String> {
    v.as_sequence()
        .unwrap_or_else(|| panic!("a list, got {v:?}"))
        .iter()
        .map(|x| x.as_str().expect("strings").to_string())
        .collect()
}

#[test]
fn compose_services_depend_on_what_exists_and_run_valid_rigcal_commands() {
    let c = compose();
    let services = c["services"].as_mapping().expect("services");
    let name = |k: &Value| k.as_str().unwrap().to_string();
    let names: Vec<String> = services.keys().map(name).collect();
    for want in ["db", "s3", "create-bucket", "migrate", "api", "worker"] {
        assert!(names.contains(&want.to_string()), "service {want} missing");
    }
    for (k, s) in services {
        let Some(deps) = s["depends_on"].as_mapping() else {
            continue;
        };
        for (dep, cond) in deps {
            let dep = dep.as_str().unwrap();
            let target = &c["services"][dep];
            assert!(!target.is_null(), "{}: depends on unknown {dep}", name(k));
            match cond["condition"].as_str() {
                Some("service_healthy") => assert!(
                    target["healthcheck"]["test"].is_sequence(),
                    "{}: waits for {dep} to be healthy, which has no healthcheck",
                    name(k)
                ),
                Some("service_completed_successfully") => assert!(
                    target["deploy"]["replicas"].is_null(),
                    "{}: waits for {dep} to complete, which is a replicated service",
                    name(k)
                ),
                other => panic!("{}: condition {other:?}", name(k)),
            }
        }
    }
    assert_eq!(c["services"]["api"]["deploy"]["replicas"].as_u64(), Some(2));
    assert!(c["services"]["worker"]["deploy"]["replicas"].as_u64() >= Some(2));

    // Every rigcal command line parses (flags, ranges) in this build, with the compose
    // environment, whose URLs parse and name the compose services.
    let mut rigcal_services = 0;
    for svc in ["migrate", "api", "worker"] {
        let s = &c["services"][svc];
        assert_eq!(
            s["build"].as_str(),
            Some("."),
            "{svc} builds the Dockerfile"
        );
        let env = s["environment"].as_mapping().expect("environment");
        let var = |k: &str| {
            env.get(Value::from(k))
                .and_then(Value::as_str)
                .unwrap_or_else(|| panic!("{svc}: {k} missing"))
                .to_string()
        };
        let db = var("RIGCAL_DATABASE_URL");
        assert!(
            matches!(DatabaseUrl::parse(&db), Ok(DatabaseUrl::Postgres(_))),
            "{db}"
        );
        assert!(
            db.contains("@db:5432/"),
            "{svc}: {db} is not the db service"
        );
        let blobs = var("RIGCAL_BLOB_URL");
        let BlobUrl::S3 { bucket, .. } = BlobUrl::parse(&blobs).unwrap() else {
            panic!("{svc}: {blobs} is not S3");
        };
        let create = str_list(&c["services"]["create-bucket"]["entrypoint"]).join(" ");
        assert!(
            create.contains(&format!("s3/{bucket}")),
            "{bucket} is never created"
        );
        assert!(var("AWS_ENDPOINT_URL").starts_with("http://s3:"), "{svc}");
        let mut args = str_list(&s["command"]);
        args.push("--help".into());
        let mut cmd = std::process::Command::new(BIN);
        cmd.args(&args);
        for (k, v) in env {
            let v = match v {
                Value::String(s) => s.clone(),
                other => serde_norway::to_string(other).unwrap().trim().to_string(),
            };
            cmd.env(k.as_str().unwrap(), v);
        }
        let out = cmd.output().unwrap();
        assert!(
            out.status.success(),
            "{svc}: rigcal {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        rigcal_services += 1;
    }
    assert_eq!(rigcal_services, 3);
    let bind = c["services"]["api"]["environment"]["RIGCAL_BIND"]
        .as_str()
        .unwrap();
    let ports = str_list(&c["services"]["api"]["ports"]);
    assert!(
        ports
            .iter()
            .all(|p| p.ends_with(&format!(":{}", bind.rsplit(':').next().unwrap()))),
        "{ports:?} do not map the bound port {bind}"
    );
}

#[test]
fn the_dockerfile_copies_what_exists_and_runs_rigcal_in_both_roles() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("Dockerfile")).unwrap();
    let mut stages = 0;
    let mut entrypoint = None;
    for line in text.lines().map(str::trim) {
        let mut words = line.split_whitespace();
        match words.next() {
            Some("FROM") => stages += 1,
            Some("COPY") if !line.contains("--from=") => {
                let parts: Vec<&str> = words.collect();
                for src in &parts[..parts.len() - 1] {
                    assert!(root.join(src).exists(), "COPY {src}: not in the repository");
                }
            }
            Some("ENTRYPOINT") => entrypoint = Some(line.to_string()),
            _ => {}
        }
    }
    assert_eq!(stages, 2, "a build stage and a runtime stage");
    assert_eq!(entrypoint.as_deref(), Some(r#"ENTRYPOINT ["rigcal"]"#));
    assert!(text.contains("COPY migrations migrations"));
    // The compose worker and migrate services rely on the entrypoint taking the command.
    let c = compose();
    assert_eq!(str_list(&c["services"]["worker"]["command"])[0], "worker");
    assert_eq!(str_list(&c["services"]["migrate"]["command"])[0], "migrate");
}
