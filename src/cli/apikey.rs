//! `rigcal apikey`: API keys, created straight in the store.

use anyhow::{anyhow, Result};
use rigcal_core::session::check_identifier;
use rigcal_service::api::auth::LOCAL_TENANT;
use rigcal_service::store::Store;
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
}

pub fn run(c: Command) -> Result<i32> {
    let Command::Create { tenant, data_dir } = c;
    let name = tenant.as_str();
    check_identifier("--tenant", name).map_err(|e| anyhow!("{e}"))?;
    if name == LOCAL_TENANT {
        return Err(anyhow!(
            "--tenant: a name other than \"local\" (the tenant of --insecure-no-auth)"
        ));
    }
    let key = super::runtime()?.block_on(async {
        let store = Store::open(&data_dir).await?;
        anyhow::Ok(store.create_api_key(name).await?)
    })?;
    println!("{key}");
    eprintln!("API key for tenant {name:?} created; it is shown only now (stored hashed).");
    Ok(0)
}
