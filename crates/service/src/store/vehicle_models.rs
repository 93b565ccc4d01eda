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
        // One statement, so two first PUTs at once cannot both insert.
        let row = self.db.fetch_one(sql("INSERT INTO vehicle_models (tenant_id, model, document, created_at, updated_at) VALUES ($1, $2, $3, $4, $4) ON CONFLICT (tenant_id, model) DO UPDATE SET document = excluded.document, updated_at = excluded.updated_at RETURNING created_at")
            .bind(tenant_id)
            .bind(model)
            .bind(&text)
            .bind(now))
            .await?;
        let created_at: i64 = row.get("created_at")?;
        Ok(created_at == now)
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
