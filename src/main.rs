//! The `posefuse` command line: serve, predict, eval, simulate, health, waymo.

mod cli;

use clap::{Parser, Subcommand};
use cli::args::{BenchArgs, EvalArgs, HealthArgs, PredictArgs, ServeArgs, SimulateArgs};
use cli::commands;

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
    Serve(ServeArgs),
    /// Run one frame JSON through the serving pipeline and print the response (no server).
    Predict(PredictArgs),
    /// Run the serving pipeline over simulator fixtures and print metrics per mode.
    Eval(EvalArgs),
    /// Render synthetic camera + LiDAR pedestrians: training shards, request fixtures, previews.
    Simulate(SimulateArgs),
    /// Ask a running server whether it is ready (gRPC health); exit status 0 only when it is.
    Health(HealthArgs),
    /// Load a server with request fixtures at several concurrencies, beside raw ONNX Runtime.
    Bench(BenchArgs),
    /// Waymo Open Dataset v2: simulate segments in its layout, convert a dataset (docs/WAYMO.md).
    Waymo(cli::waymo::WaymoArgs),
    /// ROS 2 drive logs (MCAP): score a log's pedestrians, write test logs (docs/ROS.md).
    Mcap(cli::mcap::McapArgs),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Serve(a) => commands::serve(a),
        Command::Predict(a) => commands::predict(a),
        Command::Eval(a) => commands::eval(a),
        Command::Simulate(a) => commands::simulate(a),
        Command::Health(a) => commands::health(a),
        Command::Bench(a) => Ok(posefuse::loadbench::run_bench(a.into()).map(|_report| ())?),
        Command::Waymo(a) => cli::waymo::run(a),
        Command::Mcap(a) => cli::mcap::run(a),
    }
}
