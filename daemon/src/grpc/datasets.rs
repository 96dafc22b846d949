//! `DatasetService`: registering server-side files, receiving uploads (size-limited and
//! SHA-256 checked while they arrive), listing and deleting datasets.

use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_server::DatasetService;
use tonic::{Request, Response, Status, Streaming};

use super::conversions::invalid;
use super::streaming::{first_part, HashingWriter};
use super::Api;
use crate::error::DaemonError;
use crate::service::Daemon;
use std::sync::Arc;

#[tonic::async_trait]
impl DatasetService for Api {
    async fn register_dataset(
        &self,
        request: Request<pb::RegisterDatasetRequest>,
    ) -> Result<Response<pb::Dataset>, Status> {
        let r = request.into_inner();
        let dataset = self
            .run(move |daemon| daemon.register_dataset(&r.path, &r.name))
            .await?;
        Ok(Response::new(pb::Dataset::from(&dataset)))
    }

    async fn upload_dataset(
        &self,
        request: Request<Streaming<pb::UploadDatasetRequest>>,
    ) -> Result<Response<pb::Dataset>, Status> {
        use pb::upload_dataset_request::Part;
        let mut stream = request.into_inner();
        let header = first_part(&mut stream, "header", |m| match m.part {
            Some(Part::Header(header)) => Some(header),
            _ => None,
        })
        .await?;
        let limit = self.daemon.config.max_upload_bytes;
        if header.size_bytes > limit {
            return Err(DaemonError::ResourceExhausted(format!(
                "upload of {} bytes exceeds the limit of {limit} bytes",
                header.size_bytes
            ))
            .into());
        }
        if header.sha256.len() != 64 || !header.sha256.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(invalid("header.sha256", "must be 64 hex digits").into());
        }
        // Already known content: no need to keep the bytes.
        let known_id = crate::service::dataset_id(&header.sha256.to_ascii_lowercase());
        let temp = self.daemon.upload_path();
        let mut file = HashingWriter::create(&temp)
            .await
            .map_err(|e| Status::internal(e.to_string()))?;
        let result: Result<u64, Status> = async {
            while let Some(message) = stream.message().await? {
                let Some(pb::upload_dataset_request::Part::Data(data)) = message.part else {
                    return Err(invalid("data", "only the first message may be a header").into());
                };
                if file.received() + data.len() as u64 > limit.min(header.size_bytes) {
                    return Err(DaemonError::ResourceExhausted(format!(
                        "upload exceeds its declared size of {} bytes",
                        header.size_bytes
                    ))
                    .into());
                }
                file.write(&data)
                    .await
                    .map_err(|e| Status::internal(e.to_string()))?;
            }
            let received = file.received();
            let sha = file
                .finish()
                .await
                .map_err(|e| Status::internal(e.to_string()))?;
            if received != header.size_bytes {
                return Err(invalid(
                    "header.size_bytes",
                    format!("declared {} bytes, received {received}", header.size_bytes),
                )
                .into());
            }
            if sha != header.sha256.to_ascii_lowercase() {
                return Err(invalid(
                    "header.sha256",
                    format!("does not match the data (got {sha})"),
                )
                .into());
            }
            Ok(received)
        }
        .await;
        let received = match result {
            Ok(received) => received,
            Err(status) => {
                let _ = tokio::fs::remove_file(&temp).await;
                return Err(status);
            }
        };
        if let Ok(existing) = self.daemon.dataset(&known_id) {
            let _ = tokio::fs::remove_file(&temp).await;
            return Ok(Response::new(pb::Dataset::from(&existing)));
        }
        let sha = header.sha256.to_ascii_lowercase();
        let finish =
            move |daemon: &Arc<Daemon>| daemon.finish_upload(&temp, &header.name, sha, received);
        let dataset = self.run(finish).await?;
        Ok(Response::new(pb::Dataset::from(&dataset)))
    }

    async fn get_dataset(
        &self,
        request: Request<pb::GetDatasetRequest>,
    ) -> Result<Response<pb::Dataset>, Status> {
        Ok(Response::new(pb::Dataset::from(
            &self.daemon.dataset(&request.into_inner().id)?,
        )))
    }

    async fn list_datasets(
        &self,
        request: Request<pb::ListDatasetsRequest>,
    ) -> Result<Response<pb::ListDatasetsResponse>, Status> {
        let r = request.into_inner();
        let page = self.daemon.list_datasets(r.page_size, &r.page_token)?;
        Ok(Response::new(pb::ListDatasetsResponse {
            datasets: page.items.iter().map(pb::Dataset::from).collect(),
            next_page_token: page.next_token,
        }))
    }

    async fn delete_dataset(
        &self,
        request: Request<pb::DeleteDatasetRequest>,
    ) -> Result<Response<pb::DeleteDatasetResponse>, Status> {
        self.daemon.delete_dataset(&request.into_inner().id)?;
        Ok(Response::new(pb::DeleteDatasetResponse {}))
    }
}
