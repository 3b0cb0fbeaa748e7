//! The `posefuse` command line: its flags ([`args`]) and what each subcommand runs ([`commands`]).

pub mod args;
pub mod commands;
pub mod mcap;
pub mod telemetry;
pub mod waymo;
