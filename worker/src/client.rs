//! The worker service's client as a worker holds it: its bearer token on every call.

use pointfarm_proto::v1::worker_service_client::WorkerServiceClient;
use pointfarm_proto::BearerToken;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

pub(crate) type Client = WorkerServiceClient<InterceptedService<Channel, BearerToken>>;
