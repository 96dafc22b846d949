//! `DatasetService`: registering server-side files and objects by URL, receiving uploads (name, size and quota
//! checked from the header, the LAS signature from the first bytes, SHA-256 while they
//! arrive; nothing left behind when refused), listing, describing and deleting datasets.

use std::path::Path;
use std::sync::Arc;

use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_server::DatasetService;
use pointfarm_render::ingest::LAS_SIGNATURE;
use tonic::{Request, Response, Status, Streaming};

use super::conversions::{
    dataset_description, dataset_with_publication, file_description, invalid, page_messages,
};
use super::streaming::{first_part, spawn_stream, HashingWriter, ResponseStream, CHUNK_BYTES};
use super::{export_summary, io_within, Api};
use crate::error::DaemonError;
use crate::remote_datasets::requested_urls;
use crate::service::{dataset_id, Daemon};

#[tonic::async_trait]
impl DatasetService for Api {
    async fn register_dataset(
        &self,
        request: Request<pb::RegisterDatasetRequest>,
    ) -> Result<Response<pb::Dataset>, Status> {
        let r = request.into_inner();
        let paths: Vec<String> = std::iter::once(r.path)
            .filter(|path| !path.is_empty())
            .chain(r.paths)
            .collect();
        // Objects by URL are registered from HEADs and their headers, within the remote
        // reads' own deadline.
        if let Some(urls) = requested_urls(&paths)? {
            return self
                .answer(move |daemon| daemon.register_urls(&urls, &r.name))
                .await;
        }
        // The walk is quick and bounded in time; the hashing takes as long as the files are
        // large, and reads regular files only.
        let registration = self
            .run(move |daemon| daemon.find_registration(&paths, &r.name))
            .await?;
        let dataset = self
            .run_scaled(registration.bytes, move |daemon| {
                daemon.register(registration)
            })
            .await?;
        Ok(Response::new(pb::Dataset::from(&dataset)))
    }

    async fn compose_dataset(
        &self,
        request: Request<pb::ComposeDatasetRequest>,
    ) -> Result<Response<pb::Dataset>, Status> {
        let r = request.into_inner();
        self.answer(move |daemon| daemon.compose_dataset(&r.dataset_ids, &r.name))
            .await
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
        if header.sha256.len() != 64 || !header.sha256.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(invalid("header.sha256", "must be 64 hex digits").into());
        }
        let sha = header.sha256.to_ascii_lowercase();
        // Refused from the header alone: nothing of the body is received or written.
        self.daemon.check_upload(&header.name, header.size_bytes)?;
        let temp = self.daemon.upload_path();
        let received = receive_upload(&mut stream, &temp, header.size_bytes, &sha).await;
        let received = match received {
            Ok(received) => {
                self.daemon.metrics.uploaded(received);
                received
            }
            Err(status) => {
                let _ = tokio::fs::remove_file(&temp).await;
                return Err(status);
            }
        };
        // Already known content: no need to keep the bytes.
        if let Ok(existing) = self.daemon.dataset(&dataset_id(&sha)) {
            let _ = tokio::fs::remove_file(&temp).await;
            return Ok(Response::new(pb::Dataset::from(&existing)));
        }
        let finish = move |daemon: &Arc<Daemon>| {
            let added = daemon.finish_upload(&temp, &header.name, sha, received);
            if added.is_err() {
                let _ = std::fs::remove_file(&temp);
            }
            added
        };
        self.answer(finish).await
    }

    async fn get_dataset(
        &self,
        request: Request<pb::GetDatasetRequest>,
    ) -> Result<Response<pb::Dataset>, Status> {
        let dataset = self.daemon.dataset(&request.into_inner().id)?;
        let publication = self.daemon.stores.publication(&dataset.sha256);
        Ok(Response::new(dataset_with_publication(
            &dataset,
            &publication,
        )))
    }

    async fn list_datasets(
        &self,
        request: Request<pb::ListDatasetsRequest>,
    ) -> Result<Response<pb::ListDatasetsResponse>, Status> {
        let r = request.into_inner();
        let (datasets, next_page_token) =
            page_messages(self.daemon.list_datasets(r.page_size, &r.page_token)?);
        Ok(Response::new(pb::ListDatasetsResponse {
            datasets,
            next_page_token,
        }))
    }

    async fn describe_dataset(
        &self,
        request: Request<pb::DescribeDatasetRequest>,
    ) -> Result<Response<pb::DatasetDescription>, Status> {
        let r = request.into_inner();
        let id = r.dataset_id.clone();
        let bytes = self.dataset_bytes(&id).await?;
        // Reading the files blocks (every point of them when asked): off the executor.
        let (reports, by_url) = self
            .run_scaled(bytes, move |daemon| {
                let reports = daemon.describe_dataset(&id, r.read_points)?;
                Ok((reports, daemon.dataset(&id)?.is_by_url()))
            })
            .await?;
        let files = reports
            .iter()
            .map(|report| {
                let mut description = file_description(report);
                // An object by URL is shown by its URL, which the client registered.
                if by_url {
                    return description;
                }
                // The client is shown where the file lies under its data root, not the
                // server's full path, in the errors too.
                let full = report.path.display().to_string();
                let shown = self.daemon.shown_path(&report.path);
                description.error = description.error.replace(&full, &shown);
                if let Some(copc) = description.copc.as_mut() {
                    copc.error = copc.error.replace(&full, &shown);
                }
                description
            })
            .collect();
        Ok(Response::new(dataset_description(&r.dataset_id, files)))
    }

    type ExportDatasetStream = ResponseStream<pb::ExportChunk>;

    async fn export_dataset(
        &self,
        request: Request<pb::ExportDatasetRequest>,
    ) -> Result<Response<Self::ExportDatasetStream>, Status> {
        let id = request.into_inner().dataset_id;
        // Refused before any work: an unknown dataset is NOT_FOUND.
        let bytes = self.dataset_bytes(&id).await?;
        let exported = self
            .run_scaled(bytes, move |daemon| daemon.export_dataset(&id))
            .await?;
        let summary = export_summary(&exported.report, exported.seconds);
        let path = exported.path;
        Ok(Response::new(spawn_stream(4, move |sender| async move {
            send_file(&sender, summary, &path).await;
            let _ = tokio::fs::remove_file(&path).await;
        })))
    }

    async fn delete_dataset(
        &self,
        request: Request<pb::DeleteDatasetRequest>,
    ) -> Result<Response<pb::DeleteDatasetResponse>, Status> {
        let id = request.into_inner().id;
        self.done(move |daemon| daemon.delete_dataset(&id)).await
    }
}

/// Sends an export's summary, then its file in chunks of [`CHUNK_BYTES`]; stops when the
/// client goes away.
async fn send_file(
    sender: &tokio::sync::mpsc::Sender<Result<pb::ExportChunk, Status>>,
    summary: pb::ExportSummary,
    path: &Path,
) {
    use pb::export_chunk::Part;
    use tokio::io::AsyncReadExt;
    let first = pb::ExportChunk {
        part: Some(Part::Summary(summary)),
    };
    if sender.send(Ok(first)).await.is_err() {
        return;
    }
    let mut file = match io_within(tokio::fs::File::open(path)).await {
        Ok(file) => file,
        Err(e) => {
            let _ = sender
                .send(Err(Status::internal(format!("the export: {e}"))))
                .await;
            return;
        }
    };
    loop {
        let mut chunk = Vec::with_capacity(CHUNK_BYTES);
        match io_within((&mut file).take(CHUNK_BYTES as u64).read_to_end(&mut chunk)).await {
            Ok(0) => return,
            Ok(_) => {
                let message = pb::ExportChunk {
                    part: Some(Part::Data(chunk)),
                };
                if sender.send(Ok(message)).await.is_err() {
                    return;
                }
            }
            Err(e) => {
                let _ = sender
                    .send(Err(Status::internal(format!("the export: {e}"))))
                    .await;
                return;
            }
        }
    }
}

/// Receives an upload's data messages into `temp`: exactly `size_bytes` bytes that start
/// with the LAS signature and hash to `sha256`. Returns the bytes received; on an error the
/// caller removes `temp`.
async fn receive_upload(
    stream: &mut Streaming<pb::UploadDatasetRequest>,
    temp: &Path,
    size_bytes: u64,
    sha256: &str,
) -> Result<u64, Status> {
    let internal = |e: std::io::Error| Status::internal(e.to_string());
    let mut file = io_within(HashingWriter::create(temp))
        .await
        .map_err(internal)?;
    let mut signature = Vec::with_capacity(LAS_SIGNATURE.len());
    while let Some(message) = stream.message().await? {
        let Some(pb::upload_dataset_request::Part::Data(data)) = message.part else {
            return Err(invalid("data", "only the first message may be a header").into());
        };
        if file.received() + data.len() as u64 > size_bytes {
            return Err(DaemonError::ResourceExhausted(format!(
                "upload exceeds its declared size of {size_bytes} bytes"
            ))
            .into());
        }
        // The signature is checked as soon as its bytes are in, not after the whole body.
        if signature.len() < LAS_SIGNATURE.len() {
            let missing = LAS_SIGNATURE.len() - signature.len();
            signature.extend_from_slice(&data[..missing.min(data.len())]);
            if !LAS_SIGNATURE.starts_with(&signature) {
                return Err(invalid(
                    "data",
                    "is not a LAS/LAZ file: it does not start with \"LASF\"",
                )
                .into());
            }
        }
        io_within(file.write(&data)).await.map_err(internal)?;
    }
    let received = file.received();
    let sha = io_within(file.finish()).await.map_err(internal)?;
    if received != size_bytes {
        return Err(invalid(
            "header.size_bytes",
            format!("declared {size_bytes} bytes, received {received}"),
        )
        .into());
    }
    if sha != sha256 {
        return Err(invalid(
            "header.sha256",
            format!("does not match the data (got {sha})"),
        )
        .into());
    }
    Ok(received)
}
