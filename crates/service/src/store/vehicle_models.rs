//! Vehicle models: a tenant's nominal rigs, stored as the checked JSON document, and the
//! finished jobs of a model that the fleet statistics are computed from.

use super::db::sql;
use super::{now_ms, Store};
use rigcal_core::vehicle::VehicleModel;

/// A stored model.
#[derive(Clone, Debug)]
pub struct ModelRow {
    pub model: String,
    pub document: VehicleModel,
    pub created_at: i64,
    pub updated_at: i64,
}

/// One finished job of a model, as the fleet statistics read it.
#[derive(Clone, Debug)]
pub struct FleetJob {
    pub job_id: String,
    pub vehicle_id: String,
    pub finished_at: i64,
    /// JSON array of the result's extrinsic values.
    pub extrinsics: String,
}

fn decode(r: &super::db::Rec) -> sqlx::Result<ModelRow> {
    let text: String = r.get("document")?;
    // Stored only after `VehicleModel::parse`; a row that no longer parses is a corrupt
    // store, reported as a decode error, never skipped.
    let document = serde_json::from_str(&text).map_err(|e| sqlx::Error::ColumnDecode {
        index: "document".into(),
        source: Box::new(e),
    })?;
    Ok(ModelRow {
        model: r.get("model")?,
        document,
        created_at: r.get("created_at")?,
        updated_at: r.get("updated_at")?,
    })
}

impl Store {
    /// Create or replace a model; `true` when it was created.
    pub async fn put_vehicle_model(
        &self,
        tenant_id: &str,
        model: &str,
        document: &VehicleModel,
    ) -> sqlx::Result<bool> {
        let text = serde_json::to_string(document).map_err(|e| sqlx::Error::Encode(Box::new(e)))?;
        let now = now_ms();
        // The insert says itself whether it created the row (a row comes back only
        // then): two first PUTs at once cannot both insert, and the loser replaces. (Telling
        // it from `created_at == now` called a replacement within the same millisecond a
        // creation.) Models are never deleted, so the row the update needs is there.
        let inserted = self.db.fetch_optional(sql("INSERT INTO vehicle_models (tenant_id, model, document, created_at, updated_at) VALUES ($1, $2, $3, $4, $4) ON CONFLICT (tenant_id, model) DO NOTHING RETURNING created_at")
            .bind(tenant_id)
            .bind(model)
            .bind(&text)
            .bind(now))
            .await?;
        if inserted.is_some() {
            return Ok(true);
        }
        let updated = self
            .db
            .execute(
                sql("UPDATE vehicle_models SET document = $1, updated_at = $2 WHERE tenant_id = $3 AND model = $4")
                    .bind(&text)
                    .bind(now)
                    .bind(tenant_id)
                    .bind(model),
            )
            .await?;
        if updated == 0 {
            // Neither inserted nor there: the store contradicts itself.
            return Err(sqlx::Error::RowNotFound);
        }
        Ok(false)
    }

    pub async fn vehicle_model(
        &self,
        tenant_id: &str,
        model: &str,
    ) -> sqlx::Result<Option<ModelRow>> {
        let row = self
            .db
            .fetch_optional(
                sql("SELECT * FROM vehicle_models WHERE tenant_id = $1 AND model = $2")
                    .bind(tenant_id)
                    .bind(model),
            )
            .await?;
        row.as_ref().map(decode).transpose()
    }

    pub async fn vehicle_models(&self, tenant_id: &str) -> sqlx::Result<Vec<ModelRow>> {
        let rows = self
            .db
            .fetch_all(
                sql("SELECT * FROM vehicle_models WHERE tenant_id = $1 ORDER BY model")
                    .bind(tenant_id),
            )
            .await?;
        rows.iter().map(decode).collect()
    }

    /// The succeeded jobs of a model's vehicles with their extrinsics, oldest first.
    pub async fn fleet_jobs(&self, tenant_id: &str, model: &str) -> sqlx::Result<Vec<FleetJob>> {
        let rows = self
            .db
            .fetch_all(sql("SELECT id, vehicle_id, finished_at, extrinsics FROM jobs WHERE tenant_id = $1 AND vehicle_model = $2 AND status = 'succeeded' AND vehicle_id IS NOT NULL AND extrinsics IS NOT NULL ORDER BY finished_at, id")
                .bind(tenant_id)
                .bind(model))
            .await?;
        rows.iter()
            .map(|r| {
                Ok(FleetJob {
                    job_id: r.get("id")?,
                    vehicle_id: r.get("vehicle_id")?,
                    finished_at: r.get("finished_at")?,
                    extrinsics: r.get("extrinsics")?,
                })
            })
            .collect()
    }
}
