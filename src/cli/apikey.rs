//! `rigcal apikey`: API keys, created, listed and revoked straight in the store.

use super::StoreArgs;
use anyhow::{anyhow, Result};
use rigcal_core::session::check_identifier;
use rigcal_service::api::auth::LOCAL_TENANT;
use rigcal_service::store::{rfc3339, Store};

#[derive(clap::Subcommand)]
pub enum Command {
    /// Create a key for a tenant (created if new). The key is printed once.
    Create {
        #[arg(long)]
        tenant: String,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// The keys (id, tenant, first characters, created, revoked), never their secrets.
    List {
        /// Only this tenant's keys.
        #[arg(long)]
        tenant: Option<String>,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Revoke a key by its id (from `list`): requests with it are refused from now on.
    Revoke {
        id: String,
        #[command(flatten)]
        store: StoreArgs,
    },
}

pub fn run(c: Command) -> Result<i32> {
    match c {
        Command::Create { tenant, store } => create(&tenant, &store),
        Command::List { tenant, store } => {
            let keys = super::runtime()?.block_on(async {
                anyhow::Ok(
                    Store::connect(&store.location())
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
        Command::Revoke { id, store } => {
            let done = super::runtime()?.block_on(async {
                anyhow::Ok(
                    Store::connect(&store.location())
                        .await?
                        .revoke_api_key(&id)
                        .await?,
                )
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

fn create(tenant: &str, store: &StoreArgs) -> Result<i32> {
    let name = tenant;
    check_identifier("--tenant", name).map_err(|e| anyhow!("{e}"))?;
    if name == LOCAL_TENANT {
        return Err(anyhow!(
            "--tenant: a name other than \"local\" (the tenant of --insecure-no-auth)"
        ));
    }
    let key = super::runtime()?.block_on(async {
        let store = Store::connect(&store.location()).await?;
        anyhow::Ok(store.create_api_key(name).await?)
    })?;
    println!("{key}");
    eprintln!("API key for tenant {name:?} created; it is shown only now (stored hashed).");
    Ok(0)
}
