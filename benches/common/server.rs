//! The service started in this process for the load benches
//! (`service_load`, `service_tracking`), on a temporary data directory,
//! with the serving defaults but for the upload limit; images in the object
//! store `PTV_OBJECT_STORE` names, if set (as for `ptv serve`).

use std::path::Path;

use ptv::service::{Application, ServeArgs, Timeouts};

/// A running service: its address and worker count; `stop` ends it.
pub struct Server {
    pub address: String,
    pub workers: usize,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<()>,
}

impl Server {
    /// Starts the service on `data_dir` with `workers` (default: the
    /// cores), listening on a free loopback port; on `database`
    /// (`postgres://...`) if given, else SQLite in `data_dir`.
    pub async fn start(data_dir: &Path, workers: Option<usize>, database: Option<&str>) -> Server {
        let args = ServeArgs {
            bind: "127.0.0.1:0".parse().unwrap(),
            storage: ptv::service::infra::config::Storage {
                data_dir: data_dir.to_owned(),
                database: database.map(|url| url.parse().expect("a postgres:// URL")),
                // As `ptv serve` reads them: images in an object store when
                // PTV_OBJECT_STORE is set (endpoint: AWS_ENDPOINT_URL).
                objects: ptv::service::infra::config::ObjectStoreArgs {
                    url: std::env::var("PTV_OBJECT_STORE")
                        .ok()
                        .map(|url| url.parse().expect("PTV_OBJECT_STORE is s3://bucket/prefix")),
                    s3_endpoint: std::env::var("AWS_ENDPOINT_URL").ok(),
                },
                // `--fsync` as `ptv serve` reads PTV_FSYNC (the worker
                // processes inherit it).
                durability: ptv::service::infra::config::Durability {
                    fsync: std::env::var("PTV_FSYNC")
                        .is_ok_and(|v| !matches!(v.as_str(), "" | "0" | "false" | "no" | "off")),
                },
                database_wait_secs: ptv::service::infra::config::Storage::DATABASE_WAIT_SECS,
            },
            workers,
            max_upload_mb: 256,
            api_token: None,
            max_cpu_requests: None,
            max_connections: None,
            max_export_points: ptv::service::infra::config::DEFAULT_MAX_EXPORT_POINTS,
            timeouts: Timeouts::default(),
            job_limits: Default::default(),
            lease: Default::default(),
        };
        let workers = args.worker_count();
        let app = Application::build(args).await.unwrap();
        let address = format!("http://{}", app.local_addr().unwrap());
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            app.run_until(async {
                let _ = stopped.await;
            })
            .await
            .unwrap();
        });
        Server {
            address,
            workers,
            stop,
            task,
        }
    }

    /// Stops the service and waits for it to end.
    pub async fn stop(self) {
        let _ = self.stop.send(());
        self.task.await.unwrap();
    }
}
