//! The `posefuse` command line: serve, predict, eval, simulate, health.

use clap::{Parser, Subcommand};

// Requests allocate crops and tensors of a few hundred KB; the system allocator maps and unmaps
// them each time (a page fault per 4 KB), mimalloc keeps them for reuse.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Multi-modal (camera + LiDAR) 3D pedestrian pose estimation.
#[derive(Parser)]
#[command(name = "posefuse", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Serve HTTP and gRPC on one port from a model bundle.
    Serve(posefuse::server::ServeArgs),
    /// Run one frame JSON through the serving pipeline and print the response (no server).
    Predict(posefuse::server::PredictArgs),
    /// Run the serving pipeline over simulator fixtures and print metrics per mode.
    Eval(posefuse::server::EvalArgs),
    /// Render synthetic camera + LiDAR pedestrians: training shards, request fixtures, previews.
    Simulate(posefuse::sim::SimulateArgs),
    /// Ask a running server whether it is ready (gRPC health); exit status 0 only when it is.
    Health(posefuse::server::health::HealthArgs),
    /// Load a server with request fixtures at several concurrencies, beside raw ONNX Runtime.
    Bench(posefuse::loadbench::BenchArgs),
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Serve(a) => posefuse::server::serve_command(a),
        Command::Predict(a) => posefuse::server::predict_command(a),
        Command::Eval(a) => posefuse::server::eval_command(a),
        Command::Simulate(a) => posefuse::sim::simulate_command(a),
        Command::Health(a) => posefuse::server::health::health_command(a),
        Command::Bench(a) => posefuse::loadbench::bench_command(a),
    }
}
