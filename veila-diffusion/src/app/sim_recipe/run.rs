//! One run of the recipe on simulator frames ([`SimRecipe::train`]), as `cargo xtask
//! train-default` and `bench-report`'s ablations run it: the frames rendered (or given), the work
//! folder claimed, [`run_recipe`] with its progress shown, the provenance recorded, the bundle
//! saved and read back through the verifying loader.

use std::ops::ControlFlow;
use std::path::Path;
use std::time::Instant;

use candle_core::Device;

use super::SimRecipe;
use super::snapshots::Snapshots;
use crate::app::bundle::{Bundle, BundleConfig};
use crate::app::dataset::TrainExample;
use crate::app::progress::{Bar, Progress};
use crate::app::recipe::{EncoderData, EncoderEvent, EncoderSource, RecipeInput, run_recipe};
use crate::app::sim_examples::{SimExample, depth_with_sky_at, render_split_shown, split_items};
use crate::app::stage::Stage;
use crate::denoiser::Denoiser;
use crate::error::{Error, Result, invalid};
use crate::trainer::{LossAverage, StepStats, TrainObserver, claim_checkpoint_dir};

/// Where and on what one run trains: the paths and the device its binary chose.
#[derive(Debug, Clone, Copy)]
pub struct SimRun<'a> {
    /// The workspace the scene lists are relative to.
    pub root: &'a Path,
    /// The bundle folder written.
    pub out: &'a Path,
    /// The work folder: resumable checkpoints and the trained encoders (a rerun resumes).
    pub work: &'a Path,
    /// Where the networks train.
    pub device: &'a Device,
    /// Its name in the provenance (`cpu`, `cuda:0`).
    pub device_name: &'a str,
    /// Also write a bundle of the EMA weights every this many denoiser updates (a multiple of
    /// `checkpoint_every`) into `work/snapshots/step-NNNNNNNNNN`, for learning curves.
    pub snapshot_every: Option<u64>,
    /// Frames already simulated (`None`: the first `frames` frames of `scenes`).
    pub frames: Option<&'a [SimExample]>,
}

impl SimRecipe {
    /// Refuses options that contradict each other, before any work; `given_frames`: the frames
    /// come simulated already ([`SimRun::frames`]).
    pub fn check(&self, given_frames: bool) -> Result<()> {
        let reused = self.encoders_from.is_some();
        if self.sky_depth && reused {
            return Err(invalid(
                "sky_depth",
                "it changes how the depth encoder trains, and `encoders_from` reuses trained ones: pass one of them",
            ));
        }
        if self.encoder_scenes.is_some() && reused {
            return Err(invalid(
                "encoder_scenes",
                "it chooses the frames the encoders train on, and `encoders_from` reuses trained ones: pass one of them",
            ));
        }
        if given_frames && self.encoder_list().is_some() {
            return Err(invalid(
                "encoder_scenes",
                "training on given frames trains the encoders on them too: pass `encoders_from`, or `encoder_scenes` equal to `scenes`",
            ));
        }
        Ok(())
    }

    /// Trains and writes the bundle of this recipe as `run` says; returns the config written.
    pub fn train(&self, run: &SimRun<'_>, progress: &dyn Progress) -> Result<BundleConfig> {
        let t_all = Instant::now();
        let mut style = self
            .images
            .checked_style(self.randomize_share, self.wide_facades)?;
        let mut cfg = self.bundle_config()?;
        // a model that never looks at the camera is trained on the scans alone (the same scans,
        // several times faster to simulate)
        style.scan_only = !cfg.needs_camera(self.encoders_from.is_some());
        self.check(run.frames.is_some())?;
        // (no encoder frames where there is no camera to train them on)
        let encoder_list = self.encoder_list().filter(|_| !style.scan_only);
        let method = cfg.method();
        progress.line(&format!(
            "train-default: variant {} ({}), method {} ({}), {} frames, encoders {} steps, denoiser {} steps x batch {}, seed {}",
            self.variant.name(),
            self.variant.label(),
            method.name(),
            method.label(),
            self.frames,
            self.encoder_steps,
            self.steps,
            self.batch,
            self.seed
        ));
        // a work folder of another run is refused before the frames are simulated, which takes
        // minutes to an hour
        let planned = match run.frames {
            Some(f) => f.len(),
            None => split_items(&run.root.join(&self.scenes), self.frames)?.len(),
        };
        let settings = self.settings();
        let run_key = self.run_key(&cfg, &settings, planned);
        claim_checkpoint_dir(run.work, &run_key)?;
        let t = Instant::now();
        let render = |list: &Path, label: &str| {
            render_split_shown(run.root, list, self.frames, &cfg, &style, label, progress)
        };
        let rendered;
        let examples: &[SimExample] = match run.frames {
            Some(f) => f,
            None => {
                rendered = render(&self.scenes, "simulating train frames")?;
                &rendered
            }
        };
        // the encoders' own frames when they train on another list (same count, style and seeds;
        // never with given frames, refused above)
        let encoder_rendered;
        let encoder_examples: &[SimExample] = match &encoder_list {
            Some(list) => {
                encoder_rendered = render(list, "simulating the encoders' train frames")?;
                &encoder_rendered
            }
            None => examples,
        };
        let sim_secs = t.elapsed().as_secs_f64();
        progress.line(&match &encoder_list {
            Some(l) => format!(
                "  simulated {} frames in {sim_secs:.1} s (networks: {}; encoders: {})",
                examples.len() + encoder_examples.len(),
                self.scenes.display(),
                l.display()
            ),
            None => format!(
                "  simulated {} frames in {sim_secs:.1} s{}",
                examples.len(),
                if style.scan_only {
                    " (scans alone: the model never looks at the camera)"
                } else {
                    ""
                }
            ),
        });

        if examples.len() != planned {
            return Err(Error::Data(format!(
                "{} frames simulated where the scene list gave {planned}",
                examples.len()
            )));
        }
        let images: Vec<Vec<u8>> = encoder_examples.iter().map(|e| e.rgb.clone()).collect();
        let labels: Vec<Vec<u32>> = encoder_examples.iter().map(|e| e.labels.clone()).collect();
        let sky_m = self.sky_target_m(&cfg)?;
        let depths: Vec<Vec<f32>> = encoder_examples
            .iter()
            .map(|e| match sky_m {
                Some(far) => depth_with_sky_at(&e.depth_m, far),
                None => e.depth_m.clone(),
            })
            .collect();
        let cameras: Vec<veila_geom::PinholeCamera> =
            encoder_examples.iter().map(|e| e.camera).collect();
        let enc_dir = run.work.join(self.encoder_dir_name(examples.len()));
        let encoders = match &self.encoders_from {
            Some(dir) => EncoderSource::Bundle(dir),
            None => EncoderSource::Train {
                data: EncoderData::Memory {
                    images: &images,
                    labels: Some(&labels),
                    depth_m: &depths,
                    cameras: Some(&cameras),
                },
                dir: &enc_dir,
            },
        };
        let init = self
            .init_from
            .as_ref()
            .map(|dir| Bundle::from_dir(dir, run.device))
            .transpose()?;
        let mean_init = init.as_ref().and_then(|b| b.mean.as_ref().map(|(_, w)| w));
        let train_examples: Vec<TrainExample> = examples
            .iter()
            .map(|e| e.train_example(&cfg))
            .collect::<Result<_>>()?;
        let snapshots = match run.snapshot_every {
            None => None,
            Some(every) => Some(Snapshots::plan(self, &cfg, run.work, every)?),
        };
        let t = Instant::now();
        let mut bar: Option<Box<dyn Bar + '_>> = None;
        let outcome = run_recipe(
            &mut cfg,
            RecipeInput {
                encoders,
                examples: (&train_examples).into(),
                work_dir: run.work,
                init: init.as_ref().map(|b| &b.weights),
                mean_init,
                parallel: None,
            },
            &settings,
            run.device,
            |event| match event {
                EncoderEvent::Reused(which, path) => progress.line(&format!(
                    "  {} encoder: reusing {}",
                    which.name(),
                    path.display()
                )),
                EncoderEvent::Step(which, s, total) => {
                    let label = format!("{} encoder", which.name());
                    let b = bar.get_or_insert_with(|| progress.bar(&label, total as u64));
                    b.set(s.step as u64, &format!("loss {:.4}", s.loss));
                }
                EncoderEvent::Trained(which, last) => {
                    bar = None;
                    progress.line(&format!(
                        "  {} encoder: final batch loss {last:.4}",
                        which.name()
                    ));
                }
            },
            |stage, p, step| {
                progress.line(&format!(
                    "  {}: resumed from {} (step {step})",
                    stage.name(),
                    p.display()
                ))
            },
            |stage, total| StageProgress {
                bar: progress.bar(stage.name(), total),
                loss: LossAverage::default(),
                snapshots: snapshots.as_ref().filter(|_| stage == Stage::Denoiser),
                progress,
            },
        )?;
        let den_secs = t.elapsed().as_secs_f64() - outcome.encoder_seconds;
        let den = outcome
            .fit
            .denoiser
            .as_ref()
            .ok_or_else(|| Error::Data("the mean network's run stopped early".into()))?;
        if let Some(dir) = &self.init_from {
            let initialised = |what: &str, n: usize, of: usize| {
                progress.line(&format!(
                    "  initialised {n} of {of} {what} tensors from {}",
                    dir.display()
                ))
            };
            initialised("denoiser", den.initialised, den.ema_weights.len());
            if let Some(m) = &outcome.fit.mean {
                initialised("mean-network", m.initialised, m.ema_weights.len());
            }
        }
        if let Some(m) = &outcome.fit.mean {
            progress.line(&format!(
                "  mean network: {} steps this run, mean loss {}, {:.0} s; residual scale {:?}",
                m.summary.steps_run,
                m.summary.mean_loss_text(),
                outcome.fit.seconds[0],
                cfg.residual.as_ref().map(|r| &r.scale)
            ));
        }
        progress.line(&format!(
            "  denoiser: {} steps this run, mean loss {}, {} skipped, {:.0} s",
            den.summary.steps_run,
            den.summary.mean_loss_text(),
            den.summary.skipped,
            outcome.fit.seconds[1]
        ));
        cfg.provenance = self.provenance(
            &cfg,
            &outcome,
            run.device_name,
            examples.len(),
            sim_secs,
            den_secs,
        )?;
        Bundle::save(run.out, &cfg, &outcome.into_weights())?;
        // read back through the verifying loader
        Bundle::from_dir(run.out, run.device)?;
        progress.line(&format!(
            "wrote {} in {:.0} s ({} parameters in the denoiser)",
            run.out.display(),
            t_all.elapsed().as_secs_f64(),
            veila_nn::checkpoint::parameter_count(&cfg.denoiser)?
        ));
        Ok(cfg)
    }
}

/// A network stage's progress: its bar with the averaged loss, and the denoiser's snapshots.
struct StageProgress<'a> {
    bar: Box<dyn Bar + 'a>,
    loss: LossAverage,
    snapshots: Option<&'a Snapshots>,
    progress: &'a dyn Progress,
}

impl<M: Denoiser> TrainObserver<M> for StageProgress<'_> {
    fn on_step(&mut self, s: &StepStats) -> ControlFlow<()> {
        let line = self.loss.line(s);
        self.bar.set(s.step, &line);
        ControlFlow::Continue(())
    }

    fn on_checkpoint(&mut self, step: u64, path: &Path) {
        if let Some(s) = self.snapshots
            && step.is_multiple_of(s.every)
        {
            self.progress.line(&match s.write(step, path) {
                Ok(out) => format!("  snapshot {}", out.display()),
                Err(e) => format!("  snapshot of step {step} failed: {e}"),
            });
        }
    }
}
