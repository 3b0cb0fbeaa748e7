//! What each subcommand does: the edges (files, logging, the process's runtime) around the
//! library's server, service, evaluation and simulator.

use std::time::Duration;

use posefuse::eval::FixtureRun;
use posefuse::frame::Frame;
use posefuse::json::parse_json;
use posefuse::runtime::Runtime;
use posefuse::service::Predictor;
use tonic_health::pb::health_check_response::ServingStatus;

use super::args::{EvalArgs, HealthArgs, PredictArgs, RuntimeArgs, ServeArgs, SimulateArgs};

/// Logging to stderr for the commands that do not export spans.
pub fn init_tracing(json: bool) {
    // without an endpoint there is no exporter to keep, and nothing can fail
    let _ = super::telemetry::init(json, None);
}

pub fn tokio_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread().enable_all().build()?)
}

/// `posefuse serve`: SIGHUP reloads the bundle, SIGTERM or Ctrl-C drains; a completed drain
/// exits 0.
pub fn serve(a: ServeArgs) -> anyhow::Result<()> {
    let telemetry = super::telemetry::init(a.log_json, a.otlp_endpoint.as_deref())?;
    let config = a.server_config()?;
    tracing::info!(addr = %a.addr, ?config, otlp_endpoint = ?a.otlp_endpoint, "effective configuration");
    let served = tokio_runtime()?.block_on(posefuse::server::serve_with_signals(config, a.addr));
    telemetry.shutdown();
    Ok(served?)
}

/// Starts the runtime for a CLI command and waits for warm-up.
pub fn cli_predictor(a: &RuntimeArgs) -> anyhow::Result<Predictor> {
    let config = a.runtime_config();
    tracing::info!(model_dir = %a.model_dir.display(), ?config, "effective configuration");
    let runtime = Runtime::load(&a.model_dir, &config)?;
    let stage_config = config.for_heading_stage();
    let stage = a.heading_model.as_ref().map(|dir| Runtime::load(dir, &stage_config)).transpose()?;
    if !runtime.wait_ready(Duration::from_secs(300))
        || !stage.as_ref().is_none_or(|s| s.wait_ready(Duration::from_secs(300)))
    {
        anyhow::bail!("the models did not warm up (see the log)");
    }
    let predictor = Predictor::new(runtime).with_refine(a.refine());
    Ok(match stage {
        Some(s) => predictor.with_heading_stage(s, a.heading_agree_deg),
        None => predictor,
    })
}

/// Where the scoring commands (`waymo score`, `mcap score`) get their answers.
#[derive(Debug, clap::Args)]
pub struct ScoringArgs {
    /// Frames predicted concurrently.
    #[arg(long, default_value_t = 4)]
    pub concurrency: usize,
    /// Send the requests to this running server (http://host:port) instead of loading the
    /// model in this process.
    #[arg(long)]
    pub server: Option<String>,
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

/// A running server's address, or the bundle loaded here.
pub enum Answerer {
    Server(String),
    InProcess(Box<Predictor>),
}

impl ScoringArgs {
    /// Connects nothing yet; loads and warms the bundle when there is no `--server`.
    pub fn answerer(&self) -> anyhow::Result<Answerer> {
        Ok(match &self.server {
            Some(url) => Answerer::Server(posefuse::waymo::score::server_addr(url)?),
            None => Answerer::InProcess(Box::new(cli_predictor(&self.runtime)?)),
        })
    }
}

impl Answerer {
    pub fn scorer(&self) -> posefuse::waymo::score::Scorer<'_> {
        match self {
            Answerer::Server(addr) => posefuse::waymo::score::Scorer::Server(addr.clone()),
            Answerer::InProcess(p) => posefuse::waymo::score::Scorer::InProcess(p),
        }
    }
}

/// A deadline no CLI frame should reach; the server's is a flag.
pub const CLI_FRAME_TIMEOUT: Duration = Duration::from_secs(600);

/// `posefuse predict`.
pub fn predict(a: PredictArgs) -> anyhow::Result<()> {
    init_tracing(false);
    let bytes = std::fs::read(&a.frame).map_err(|e| anyhow::anyhow!("{}: {e}", a.frame.display()))?;
    let frame: Frame = parse_json(&bytes).map_err(|e| anyhow::anyhow!("{}: {e}", a.frame.display()))?;
    let predictor = cli_predictor(&a.runtime)?;
    let resp = tokio_runtime()?.block_on(predictor.answer(frame, None, CLI_FRAME_TIMEOUT))?;
    println!("{}", serde_json::to_string_pretty(&resp)?);
    Ok(())
}

/// `posefuse eval`.
pub fn eval(a: EvalArgs) -> anyhow::Result<()> {
    init_tracing(false);
    let predictor = cli_predictor(&a.runtime)?;
    let run = FixtureRun {
        mode: a.mode,
        heading_noise: a.heading_noise,
        noise_seed: a.noise_seed,
        concurrency: a.concurrency,
        timeout: CLI_FRAME_TIMEOUT,
    };
    let report = tokio_runtime()?.block_on(posefuse::eval::evaluate_fixtures(&predictor, &a.data, &run))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", report.text());
    }
    Ok(())
}

/// `posefuse health`: exit status 0 only when the server is serving.
pub fn health(a: HealthArgs) -> anyhow::Result<()> {
    let addr = posefuse::server::health::connect_addr(a.addr);
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let status = runtime.block_on(posefuse::server::health::check(addr, Duration::from_secs(a.timeout_s)))?;
    if status != ServingStatus::Serving {
        anyhow::bail!("{addr} is not ready: {}", status.as_str_name());
    }
    println!("{addr}: {}", status.as_str_name());
    Ok(())
}

/// `posefuse simulate`.
pub fn simulate(a: SimulateArgs) -> anyhow::Result<()> {
    Ok(posefuse::sim::simulate(a.into())?)
}
