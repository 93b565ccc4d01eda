//! `rigcal migrate`: apply the schema migrations and exit (the deployment's one-off step
//! before replicas start; `serve` and `worker` also apply them, under the same lock).

use super::StoreArgs;
use anyhow::Result;
use rigcal_service::store::db::{redact, Db};

/// Apply pending migrations to the database and exit.
#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    store: StoreArgs,
}

pub fn run(a: Args) -> Result<i32> {
    let url = a.store.location().database_url;
    super::runtime()?.block_on(Db::connect(&url))?;
    eprintln!("rigcal migrate: {} is up to date", redact(&url));
    Ok(0)
}
