//! Training examples and where they come from: in memory, or read on demand from an
//! [`ExampleSource`] (shards on disk, say) with a loader thread that reads the coming batches
//! ahead, for training at any dataset size: the frozen networks (encoders, the mean network of
//! residual diffusion) then run per batch instead of once per example and kept, and memory is
//! bounded by the batch and the prefetch depth, not by the set.
//!
//! [`Examples`] chooses between this and the in-memory path: `Memory` computes every example's
//! frozen features once and keeps them (fastest for a few thousand frames), `Stream` reads and
//! encodes per batch. Both give the same batches for the same step, so they train the same
//! weights up to float rounding.

use std::sync::mpsc::{Receiver, sync_channel};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;

use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use veila_geom::PinholeCamera;

use crate::error::{Error, Result};
use crate::trainer::distributed::ProcessGroup;

/// One training example: a camera image at the bundle's size, its camera, and the encoded clean
/// range image (`in_channels * rows * cols` values, row-major per channel); a multi-view model
/// (`conditioning.num_views > 1`) takes its further cameras from `extra_views`.
#[derive(Debug, Clone)]
pub struct TrainExample {
    /// RGB bytes at the bundle image size.
    pub rgb: Vec<u8>,
    /// The camera of that image.
    pub camera: PinholeCamera,
    /// Encoded range image.
    pub x0: Vec<f32>,
    /// The rig's other cameras, in the model's view order (empty for one view).
    pub extra_views: Vec<TrainView>,
}

/// A further camera of a [`TrainExample`]: its image at the bundle size and its camera.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainView {
    /// RGB bytes at the bundle image size.
    pub rgb: Vec<u8>,
    /// The camera of that image.
    pub camera: PinholeCamera,
}

/// The camera an example without an image carries, for models that never look at the camera
/// ([`super::bundle::BundleConfig::needs_camera`]): identity pose, unit focal length, the
/// principal point at the centre of `cfg`'s image.
pub fn blind_camera(cfg: &super::bundle::BundleConfig) -> Result<PinholeCamera> {
    let (w, h) = (cfg.image_width as u32, cfg.image_height as u32);
    let k = [
        [1.0, 0.0, 0.5 * w as f32, 0.0],
        [0.0, 1.0, 0.5 * h as f32, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    Ok(PinholeCamera::new(k, glam::Mat4::IDENTITY, w, h)?)
}

impl TrainExample {
    /// An example of one camera.
    pub fn new(rgb: Vec<u8>, camera: PinholeCamera, x0: Vec<f32>) -> Self {
        Self {
            rgb,
            camera,
            x0,
            extra_views: Vec::new(),
        }
    }

    /// Its first `n` views as the generation pipeline takes them (an error when it has fewer).
    pub fn views(&self, n: usize) -> Result<Vec<super::generate::CameraView<'_>>> {
        let all = 1 + self.extra_views.len();
        if all < n {
            return Err(Error::Data(format!(
                "the model takes {n} camera views, an example has {all}"
            )));
        }
        let mut v = vec![super::generate::CameraView {
            rgb: &self.rgb,
            camera: &self.camera,
        }];
        v.extend(
            self.extra_views
                .iter()
                .take(n - 1)
                .map(|x| super::generate::CameraView {
                    rgb: &x.rgb,
                    camera: &x.camera,
                }),
        );
        Ok(v)
    }

    /// The cameras of its first `n` views.
    pub fn rig(&self, n: usize) -> Vec<PinholeCamera> {
        std::iter::once(self.camera)
            .chain(self.extra_views.iter().map(|x| x.camera))
            .take(n)
            .collect()
    }
}

/// A training set read on demand (from shards on disk, say). The denoiser's training
/// (`DenoiserTraining::streaming`) and the encoders' read their batches through it, so
/// nothing is held per example. `Send + Sync`: a loader thread reads ahead.
pub trait ExampleSource: Send + Sync {
    /// Number of examples.
    fn len(&self) -> usize;

    /// Whether there are none.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Example `index` (`< len()`); errors name the file it came from.
    fn example(&self, index: usize) -> Result<TrainExample>;

    /// The encoders' training data of example `index` (see [`super::EncoderData`]); the default
    /// says the source has none.
    fn encoder_example(&self, index: usize) -> Result<EncoderExample> {
        let _ = index;
        Err(Error::Data(
            "this example source carries no encoder targets (images with depth and labels)".into(),
        ))
    }
}

/// One camera image with the small-CNN encoders' sparse per-pixel targets.
#[derive(Debug, Clone, PartialEq)]
pub struct EncoderExample {
    /// RGB bytes at the bundle image size.
    pub rgb: Vec<u8>,
    /// The camera of that image; an encoder with the ground prior
    /// ([`veila_nn::encoders::small_cnn::SmallCnnConfig::ground_prior`]) computes its input
    /// channel from it, and fails without it. Augmentation keeps it in step with the image.
    pub camera: Option<PinholeCamera>,
    /// Train ids per pixel (0 = ignored), when the data has labels.
    pub labels: Option<Vec<u32>>,
    /// Metric depth per pixel (0 = no ground truth).
    pub depth_m: Vec<f32>,
}

/// Examples in memory, as a source (`Arc::new(examples)` streams them through the loader).
impl ExampleSource for Vec<TrainExample> {
    fn len(&self) -> usize {
        Vec::len(self)
    }

    fn example(&self, index: usize) -> Result<TrainExample> {
        self.get(index)
            .cloned()
            .ok_or_else(|| Error::Data(format!("example {index} of a set of {}", Vec::len(self))))
    }
}

/// Where a training run's examples come from.
#[derive(Clone, Copy)]
pub enum Examples<'a> {
    /// In memory; the frozen encoder features (and a residual denoiser's mean predictions) of
    /// every example are computed once and kept. The fastest; memory grows with the set (about
    /// 0.3 MiB per frame at the bundled size, 17 MiB at the paper's widths).
    Memory(&'a [TrainExample]),
    /// Read on demand: a loader thread reads `prefetch` batches ahead, and the frozen networks
    /// run on every batch. Memory is bounded by the batch and `prefetch`.
    Stream {
        /// The examples.
        source: &'a Arc<dyn ExampleSource>,
        /// Batches read ahead (at least 1).
        prefetch: usize,
    },
}

impl std::fmt::Debug for Examples<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Examples::Memory(e) => write!(f, "Examples::Memory({} examples)", e.len()),
            Examples::Stream { source, prefetch } => write!(
                f,
                "Examples::Stream({} examples, prefetch {prefetch})",
                source.len()
            ),
        }
    }
}

impl<'a> From<&'a [TrainExample]> for Examples<'a> {
    fn from(e: &'a [TrainExample]) -> Self {
        Examples::Memory(e)
    }
}

impl<'a> From<&'a Vec<TrainExample>> for Examples<'a> {
    fn from(e: &'a Vec<TrainExample>) -> Self {
        Examples::Memory(e)
    }
}

impl Examples<'_> {
    /// Number of examples.
    pub fn len(&self) -> usize {
        match self {
            Examples::Memory(e) => e.len(),
            Examples::Stream { source, .. } => source.len(),
        }
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The order examples are drawn in: one seeded shuffle per epoch, a pure function of the step
/// (so resumed runs match uninterrupted ones), and with a process group this rank's share.
#[derive(Debug, Clone)]
pub(crate) struct Order {
    pub(crate) n: usize,
    pub(crate) batch: usize,
    pub(crate) seed: u64,
    pub(crate) shard: Option<ProcessGroup>,
}

impl Order {
    /// Indices of the global batch of update `step`.
    pub(crate) fn indices(&self, step: u64) -> Vec<usize> {
        let (n, b) = (self.n, self.batch);
        let start = step as usize * b;
        // one seeded shuffle per epoch, built once for the (at most a few) epochs the batch spans
        let mut perm: Option<(usize, Vec<usize>)> = None;
        (start..start + b)
            .map(|k| {
                let epoch = k / n;
                if perm.as_ref().is_none_or(|(e, _)| *e != epoch) {
                    let mut p: Vec<usize> = (0..n).collect();
                    let mut rng = ChaCha8Rng::seed_from_u64(
                        self.seed ^ (epoch as u64).wrapping_mul(0x9E37_79B9),
                    );
                    p.shuffle(&mut rng);
                    perm = Some((epoch, p));
                }
                perm.as_ref().map_or(0, |(_, p)| p[k % n])
            })
            .collect()
    }

    /// This rank's indices of update `step`.
    pub(crate) fn local(&self, step: u64) -> Vec<usize> {
        let all = self.indices(step);
        match &self.shard {
            Some(g) => g.shard(&all).to_vec(),
            None => all,
        }
    }
}

/// A thread reading the examples of updates `next, next + 1, ...` ahead into a bounded channel.
struct Loader {
    rx: Option<Receiver<(u64, Result<Vec<TrainExample>>)>>,
    next: u64,
    handle: Option<JoinHandle<()>>,
}

impl Loader {
    fn spawn(source: Arc<dyn ExampleSource>, order: Order, start: u64, depth: usize) -> Self {
        let (tx, rx) = sync_channel(depth.max(1));
        let handle = std::thread::Builder::new()
            .name("veila-loader".into())
            .spawn(move || {
                for step in start.. {
                    let batch = order
                        .local(step)
                        .into_iter()
                        .map(|i| source.example(i))
                        .collect::<Result<Vec<_>>>();
                    let failed = batch.is_err();
                    // the receiver hung up (training ended or jumped): stop
                    if tx.send((step, batch)).is_err() || failed {
                        break;
                    }
                }
            })
            .ok();
        Loader {
            rx: Some(rx),
            next: start,
            handle,
        }
    }

    fn recv(&mut self) -> Result<(u64, Result<Vec<TrainExample>>)> {
        let got = self
            .rx
            .as_ref()
            .and_then(|rx| rx.recv().ok())
            .ok_or_else(|| Error::Data("the data loader thread stopped".into()))?;
        self.next = got.0 + 1;
        Ok(got)
    }
}

impl Drop for Loader {
    fn drop(&mut self) {
        // hang up first, so a loader blocked on a full channel wakes and ends
        drop(self.rx.take());
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> Result<MutexGuard<'_, T>> {
    m.lock()
        .map_err(|_| Error::Data("a data loader lock is poisoned".into()))
}

/// The examples of each update, read ahead by a [`Loader`]; the current update's are kept for
/// its parts (gradient accumulation).
pub(crate) struct Prefetcher {
    source: Arc<dyn ExampleSource>,
    depth: usize,
    loader: Mutex<Option<Loader>>,
    current: Mutex<Option<(u64, Arc<Vec<TrainExample>>)>>,
}

impl std::fmt::Debug for Prefetcher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Prefetcher")
            .field("examples", &self.source.len())
            .field("depth", &self.depth)
            .finish_non_exhaustive()
    }
}

impl Prefetcher {
    pub(crate) fn new(source: Arc<dyn ExampleSource>, depth: usize) -> Self {
        Self {
            source,
            depth: depth.max(1),
            loader: Mutex::new(None),
            current: Mutex::new(None),
        }
    }

    /// This rank's examples of update `step`, in `order.local(step)` order. Updates are
    /// expected in sequence; any other step (a resume, a jump) restarts the loader there.
    pub(crate) fn examples(&self, order: &Order, step: u64) -> Result<Arc<Vec<TrainExample>>> {
        let mut current = lock(&self.current)?;
        if let Some((s, ex)) = current.as_ref()
            && *s == step
        {
            return Ok(ex.clone());
        }
        let mut loader = lock(&self.loader)?;
        if loader.as_ref().is_none_or(|l| l.next != step) {
            *loader = None;
            *loader = Some(Loader::spawn(
                self.source.clone(),
                order.clone(),
                step,
                self.depth,
            ));
        }
        let l = loader
            .as_mut()
            .ok_or_else(|| Error::Data("no data loader".into()))?;
        let (s, batch) = l.recv()?;
        if s != step {
            return Err(Error::Data(format!(
                "the data loader gave update {s} for update {step}"
            )));
        }
        let batch = Arc::new(batch?);
        *current = Some((step, batch.clone()));
        Ok(batch)
    }
}

/// The most distinct cameras one training run may have (each gets its GCMA geometry, built once).
pub const MAX_RIGS: usize = 1024;

/// The GCMA geometries of a run's cameras, built the first time a camera appears and kept for the
/// run: examples of different rigs train in one batch, each sample attending with its own.
pub(crate) struct Rigs {
    slots: Vec<std::sync::OnceLock<(Vec<PinholeCamera>, veila_nn::GcmaGeometry)>>,
    insert: Mutex<()>,
}

impl std::fmt::Debug for Rigs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let n = self.slots.iter().take_while(|s| s.get().is_some()).count();
        write!(f, "Rigs({n} cameras)")
    }
}

impl Rigs {
    pub(crate) fn new() -> Self {
        Self {
            slots: (0..MAX_RIGS).map(|_| std::sync::OnceLock::new()).collect(),
            insert: Mutex::new(()),
        }
    }

    fn find(&self, rig: &[PinholeCamera]) -> Option<&veila_nn::GcmaGeometry> {
        self.slots
            .iter()
            .map_while(|s| s.get())
            .find(|(c, _)| c == rig)
            .map(|(_, g)| g)
    }

    /// The geometry of the cameras `rig` (one per view; built by `build` the first time).
    pub(crate) fn get(
        &self,
        rig: &[PinholeCamera],
        build: impl FnOnce() -> Result<veila_nn::GcmaGeometry>,
    ) -> Result<&veila_nn::GcmaGeometry> {
        if let Some(g) = self.find(rig) {
            return Ok(g);
        }
        let _one_writer = lock(&self.insert)?;
        if let Some(g) = self.find(rig) {
            return Ok(g);
        }
        let slot = self
            .slots
            .iter()
            .find(|s| s.get().is_none())
            .ok_or_else(|| {
                Error::Data(format!(
                    "more than {MAX_RIGS} distinct camera rigs in one training run"
                ))
            })?;
        let _ = slot.set((rig.to_vec(), build()?));
        slot.get()
            .map(|(_, g)| g)
            .ok_or_else(|| Error::Data("internal: a rig slot was not filled".into()))
    }

    /// The first camera's geometry, if any was built.
    pub(crate) fn first(&self) -> Option<&veila_nn::GcmaGeometry> {
        self.slots[0].get().map(|(_, g)| g)
    }
}
