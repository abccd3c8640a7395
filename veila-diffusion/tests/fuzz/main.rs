//! Mutation fuzzing of every artifact reader (issue 58): a model bundle (`bundle.json`, its
//! `manifest.json`, its safetensors weights), a segmenter folder, checkpoint and encoder weights, training shards and
//! their manifest, range images (EXR), point clouds (PLY, KITTI `.bin`, nuScenes `.pcd.bin`),
//! `.npy` / `.npz` sample sets, KITTI and nuScenes calibrations, the training and scene TOML,
//! sensor files, SemanticKITTI label maps (YAML) and `.label` files, camera images, and a generated
//! dataset's `dataset.json`.
//!
//! Each target starts from valid files made by the library's own writers (or small valid
//! literals) and feeds its reader mutated copies: bit flips, boundary values, truncations,
//! insertions, deletions, duplicated runs, splices of another seed, and structure-aware edits
//! (JSON, TOML, YAML and text tokens, safetensors and `.npy` headers, EXR attributes, PLY headers,
//! zip members) that put hostile values (0, -1, 2^31, 2^63, 1e300, NaN, huge strings, `../` and
//! absolute paths, deep nesting) into leaves, counts and shapes. The properties, for every input:
//!
//! - the reader returns `Ok` or an error, never panics (a panic is caught and counted);
//! - an error names the file it is about (or its folder);
//! - it never hangs: the time of each input is recorded, the slowest must stay under
//!   [`engine::SLOWEST_INPUT_LIMIT`], and a watchdog aborts the run (saving the input) when one
//!   takes longer than [`engine::HANG_LIMIT`];
//! - memory stays bounded: this binary's allocator counts live bytes, and the peak of each
//!   target, above what was live when it started, must stay under [`engine::PEAK_LIVE_LIMIT`]
//!   (512 MiB); an allocation that would pass [`alloc::HARD_LIMIT`] is refused (the process
//!   aborts, naming the size) instead of exhausting the machine;
//! - files a reader must not open (decoys outside a dataset root or a manifest's folder) are
//!   never what it returns.
//!
//! Inputs per target: `VEILA_FUZZ_INPUTS` (default 200, CI's debug pass); the mutation stream is
//! seeded by the target's name and `VEILA_FUZZ_SEED` (default 0), so a run is reproducible. A
//! failing input is saved under `CARGO_TARGET_TMPDIR/fuzz-failures/` and named in the failure.
//! The targets run one at a time (a lock), so each one's peak memory is its own. As a benchmark
//! (BENCHMARKS.md, "Fuzzing the artifact readers"):
//!
//! ```sh
//! VEILA_FUZZ_INPUTS=10000 cargo test --release -p veila-diffusion --test fuzz -- --nocapture --test-threads 1
//! ```

mod alloc;
mod engine;
mod mutate;
mod seeds;
mod targets_data;
mod targets_model;
mod targets_text;

#[global_allocator]
static ALLOC: alloc::Counting = alloc::Counting;
