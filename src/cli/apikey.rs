//! `rigcal apikey`: API keys, created, listed and revoked straight in the store.

use anyhow::{anyhow, Result};
use rigcal_core::session::check_identifier;
use rigcal_service::api::auth::LOCAL_TENANT;
use rigcal_service::store::{rfc3339, Store};
use std::path::PathBuf;

#[derive(clap::Subcommand)]
pub enum Command {
    /// Create a key for a tenant (created if new). The key is printed once.
    Create {
        #[arg(long)]
        tenant: String,
        #[arg(long, env = "RIGCAL_DATA_DIR", default_value = "rigcal-data")]
        data_dir: PathBuf,
    },
    /// The keys (id, tenant, first characters, created, revoked), never their secrets.
    List {
        /// Only this tenant's keys.
        #[arg(long)]
        tenant: Option<String>,
        #[arg(long, env = "RIGCAL_DATA_DIR", default_value = "rigcal-data")]
        data_dir: PathBuf,
    },
    /// Revoke a key by its id (from `list`): requests with it are refused from now on.
    Revoke {
        id: String,
        #[arg(long, env = "RIGCAL_DATA_DIR", default_value = "rigcal-data")]
        data_dir: PathBuf,
    },
}

pub fn run(c: Command) -> Result<i32> {
    match c {
        Command::Create { tenant, data_dir } => create(&tenant, &data_dir),
        Command::List { tenant, data_dir } => {
            let keys = super::runtime()?.block_on(async {
                anyhow::Ok(
                    Store::open(&data_dir)
                        .await?
                        .api_keys(tenant.as_deref())
                        .await?,
                )
            })?;
            println!(
                "{:<36}  {:<24}  {:<8}  {:<24}  revoked",
                "id", "tenant", "prefix", "created"
            );
            for k in keys {
                println!(
                    "{:<36}  {:<24}  {:<8}  {:<24}  {}",
                    k.id,
                    k.tenant,
                    k.prefix,
                    rfc3339(k.created_at),
                    k.revoked_at.map_or("-".into(), rfc3339)
                );
            }
            Ok(0)
        }
        Command::Revoke { id, data_dir } => {
            let done = super::runtime()?.block_on(async {
                anyhow::Ok(Store::open(&data_dir).await?.revoke_api_key(&id).await?)
            })?;
            if !done {
                return Err(anyhow!(
                    "ID: no active API key {id:?} (see `rigcal apikey list`)"
                ));
            }
            eprintln!("API key {id} revoked.");
            Ok(0)
        }
    }
}

fn create(tenant: &str, data_dir: &std::path::Path) -> Result<i32> {
    let name = tenant;
    check_identifier("--tenant", name).map_err(|e| anyhow!("{e}"))?;
    if name == LOCAL_TENANT {
        return Err(anyhow!(
            "--tenant: a name other than \"local\" (the tenant of --insecure-no-auth)"
        ));
    }
    let key = super::runtime()?.block_on(async {
        let store = Store::open(data_dir).await?;
        anyhow::Ok(store.create_api_key(name).await?)
    })?;
    println!("{key}");
    eprintln!("API key for tenant {name:?} created; it is shown only now (stored hashed).");
    Ok(0)
}
