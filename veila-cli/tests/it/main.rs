//! Integration tests of the `veila` binary (one test binary, a module per command or area:
//! one link instead of one per file, and the harness spreads every test over the cores).

mod bench;
mod common;
mod convert;
mod data_cmds;
mod demo;
mod doors;
mod edit;
mod eval_cmd;
mod eval_crossmodal;
mod eval_features;
mod eval_protocols;
mod generate;
mod generate_frames;
mod help_defaults;
mod hostile_inputs;
mod hostile_outputs;
mod hostile_signals;
mod reliability;
mod report_html;
mod segment;
mod simulate;
mod train;
mod untrusted_values;
mod weather_cmd;
