//! Dataset-scale generation with the bundled model: an interrupted and resumed run, and two workers
//! sharing a folder, write the bytes of one uninterrupted run; shards give what their KITTI folder
//! gives; a folder of another job, or one among the inputs, is refused untouched; the labeller hook
//! writes a label per point.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use candle_core::Device;
use veila_data::image::{Rgb, RgbImage};
use veila_diffusion::Error;
use veila_diffusion::app::dataset_gen::{
    DATASET_MANIFEST, DatasetEvent, DatasetJob, DatasetSummary, FrameSource, ScanLabeller,
    SourceKind, check_not_inside, frame_name, frame_seed, generate_dataset,
};
use veila_diffusion::app::{Bundle, Scan};

const CALIB: &str = "P0: 100 0 50 0 0 100 20 0 0 0 1 0\nP1: 100 0 50 0 0 100 20 0 0 0 1 0\n\
P2: 100 0 50 0 0 100 20 0 0 0 1 0\nP3: 100 0 50 0 0 100 20 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\n\
Tr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n";

fn bundled() -> Bundle {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/default");
    Bundle::from_dir(&dir, &Device::Cpu).unwrap()
}

/// A KITTI object split of `n` frames: a 100 x 40 image each (and a small scan, for `convert`).
fn make_kitti(root: &Path, n: usize) {
    for d in ["velodyne", "image_2", "calib"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    for f in 0..n {
        let id = format!("{f:06}");
        RgbImage::from_fn(100, 40, |x, y| {
            if y < 18 {
                Rgb([110, 150, 210])
            } else {
                Rgb([(x * 2 + 40 * f as u32) as u8, (y * 5) as u8, 70])
            }
        })
        .save(root.join(format!("image_2/{id}.png")))
        .unwrap();
        std::fs::write(root.join(format!("calib/{id}.txt")), CALIB).unwrap();
        let scan: Vec<u8> = (0..500)
            .flat_map(|i| {
                let a = i as f32 * 0.0126;
                [8.0 * a.cos(), 8.0 * a.sin(), -1.5, 0.5]
            })
            .flat_map(|v| v.to_le_bytes())
            .collect();
        std::fs::write(root.join(format!("velodyne/{id}.bin")), scan).unwrap();
    }
}

/// The bundled model, a temporary folder, and a KITTI split of `n` frames in it.
fn setup(n: usize) -> (Bundle, tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let kitti = tmp.path().join("kitti");
    make_kitti(&kitti, n);
    (bundled(), tmp, kitti)
}

fn job(bundle: &Bundle, out: &Path, worker: (usize, usize)) -> DatasetJob<'static> {
    DatasetJob {
        out_dir: out.to_path_buf(),
        sampler: veila_diffusion::SamplerConfig {
            steps: 2,
            ..bundle.config.sampler.clone()
        },
        residual_weight: 1.0,
        seed: 5,
        worker_index: worker.0,
        worker_count: worker.1,
        labeller: None,
    }
}

fn run(bundle: &Bundle, frames: &Path, job: &DatasetJob<'_>) -> Result<DatasetSummary, Error> {
    let source = FrameSource::open(frames).unwrap();
    generate_dataset(bundle, &source, job, &mut |_| {})
}

/// Every file under `dir` (relative path -> bytes).
fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    fn walk(root: &Path, dir: &Path, out: &mut BTreeMap<String, Vec<u8>>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                let rel = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

#[test]
fn resumed_and_split_runs_write_the_bytes_of_one_run() {
    let (bundle, tmp, kitti) = setup(5);
    let whole = tmp.path().join("whole");
    let s = run(&bundle, &kitti, &job(&bundle, &whole, (0, 1))).unwrap();
    assert_eq!((s.total, s.generated, s.skipped, s.complete), (5, 5, 0, 5));
    let want = files(&whole);
    let names: Vec<&str> = want.keys().map(String::as_str).collect();
    assert_eq!(
        names,
        [
            "dataset.json",
            "velodyne/000000.bin",
            "velodyne/000001.bin",
            "velodyne/000002.bin",
            "velodyne/000003.bin",
            "velodyne/000004.bin"
        ]
    );
    assert!(want.values().all(|b| !b.is_empty()));
    // every frame its own seed: no two scans alike
    assert_ne!(want["velodyne/000000.bin"], want["velodyne/000001.bin"]);

    // two workers into one folder: the same bytes
    let split = tmp.path().join("split");
    let a = run(&bundle, &kitti, &job(&bundle, &split, (1, 2))).unwrap();
    assert_eq!((a.assigned, a.generated, a.complete), (2, 2, 2));
    let b = run(&bundle, &kitti, &job(&bundle, &split, (0, 2))).unwrap();
    assert_eq!((b.assigned, b.generated, b.complete), (3, 3, 5));
    assert_eq!(files(&split), want);

    // interrupted: a frame lost, a killed writer's temporary file; the rerun does the rest only
    std::fs::remove_file(split.join("velodyne/000003.bin")).unwrap();
    std::fs::write(split.join("velodyne/.veila-x1y2z3.tmp"), b"half a scan").unwrap();
    // a scan cut short (not whole records) is not a complete frame
    let cut = &want["velodyne/000001.bin"];
    std::fs::write(split.join("velodyne/000001.bin"), &cut[..cut.len() - 3]).unwrap();
    let mut events = Vec::new();
    let source = FrameSource::open(&kitti).unwrap();
    let r = generate_dataset(&bundle, &source, &job(&bundle, &split, (0, 1)), &mut |e| {
        events.push(match e {
            DatasetEvent::Start { to_generate, .. } => format!("start {to_generate}"),
            DatasetEvent::Frame { name, .. } => name.to_string(),
        })
    })
    .unwrap();
    assert_eq!(events, ["start 2", "000001", "000003"]);
    assert_eq!((r.skipped, r.generated, r.complete), (3, 2, 5));
    assert_eq!(files(&split), want, "resumed run");
    // a complete dataset: nothing to do
    let again = run(&bundle, &kitti, &job(&bundle, &split, (0, 1))).unwrap();
    assert_eq!((again.generated, again.skipped), (0, 5));
}

#[test]
fn shards_give_what_their_kitti_folder_gives() {
    let (bundle, tmp, kitti) = setup(3);
    let shards = tmp.path().join("shards");
    let (dataset, _) =
        veila_data::convert::open_dataset(veila_data::DatasetName::Kitti, &kitti, true).unwrap();
    let mut opts =
        veila_data::convert::ConvertOptions::new(&shards, veila_geom::LidarSensor::hdl64e());
    opts.frames_per_shard = 2;
    veila_data::convert::convert(dataset.as_ref(), None, &opts, &|_| {}).unwrap();
    assert_eq!(
        FrameSource::open(&shards).unwrap().kind(),
        SourceKind::Shards
    );
    let a = tmp.path().join("a");
    let b = tmp.path().join("b");
    run(&bundle, &kitti, &job(&bundle, &a, (0, 1))).unwrap();
    run(&bundle, &shards, &job(&bundle, &b, (0, 1))).unwrap();
    let (fa, fb) = (files(&a), files(&b));
    assert_eq!(fa.len(), 4);
    for (name, bytes) in &fa {
        if name.ends_with(".bin") {
            assert_eq!(bytes, &fb[name], "{name}");
        }
    }
    // the manifests differ in the source alone
    let text = String::from_utf8(fb[DATASET_MANIFEST].clone()).unwrap();
    assert!(text.contains("\"source\": \"shards\""), "{text}");
    // a shard without camera images cannot be generated from
    let bare = tmp.path().join("bare");
    opts.out_dir = bare.clone();
    opts.include_images = false;
    veila_data::convert::convert(dataset.as_ref(), None, &opts, &|_| {}).unwrap();
    let e = run(&bundle, &bare, &job(&bundle, &tmp.path().join("c"), (0, 1)))
        .unwrap_err()
        .to_string();
    assert!(e.contains("no camera images"), "{e}");
    assert!(!tmp.path().join("c").exists());
}

#[test]
fn another_jobs_folder_or_one_among_the_inputs_is_refused_untouched() {
    let (bundle, tmp, kitti) = setup(2);
    let out = tmp.path().join("out");
    run(&bundle, &kitti, &job(&bundle, &out, (0, 1))).unwrap();
    let before = files(&out);
    let refused = |j: &DatasetJob<'_>, frames: &Path, needles: &[&str]| {
        let e = run(&bundle, frames, j).unwrap_err();
        let msg = e.to_string();
        for n in needles {
            assert!(msg.contains(n), "`{n}` not in: {msg}");
        }
        msg
    };
    // another seed, another sampler
    let mut other = job(&bundle, &out, (0, 1));
    other.seed = 6;
    refused(
        &other,
        &kitti,
        &["dataset.json", "another job", "seed: this run 6"],
    );
    let mut other = job(&bundle, &out, (0, 1));
    other.sampler.steps = 3;
    refused(&other, &kitti, &["sampler"]);
    // another list of frames
    let more = tmp.path().join("more");
    make_kitti(&more, 3);
    refused(&job(&bundle, &out, (0, 1)), &more, &["frames: this run 3"]);
    assert_eq!(files(&out), before);
    // a folder of other files; the inputs' folder, one inside it, one holding it
    let foreign = tmp.path().join("foreign");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("notes.txt"), b"mine").unwrap();
    refused(
        &job(&bundle, &foreign, (0, 1)),
        &kitti,
        &["notes.txt", "not part of a generated dataset"],
    );
    let scans = tmp.path().join("scans");
    std::fs::create_dir_all(scans.join("velodyne")).unwrap();
    std::fs::write(scans.join("velodyne/000000.bin"), b"").unwrap();
    refused(&job(&bundle, &scans, (0, 1)), &kitti, &["no dataset.json"]);
    for (out, what) in [
        (kitti.clone(), "is the frames' folder"),
        (kitti.join("gen/new"), "is inside the frames' folder"),
        (kitti.join("image_2/../x"), "is inside the frames' folder"),
        (tmp.path().to_path_buf(), "holds the frames' folder"),
    ] {
        let e = check_not_inside(&kitti, &out).unwrap_err().to_string();
        assert!(e.contains(what), "{}: {e}", out.display());
    }
    assert!(!kitti.join("gen").exists() && !kitti.join("x").exists());
    check_not_inside(&kitti, &tmp.path().join("kitti-gen")).unwrap();
    // a worker outside the split
    let e = run(&bundle, &kitti, &job(&bundle, &out, (2, 2))).unwrap_err();
    assert!(e.to_string().contains("worker 2 is not in 0..2"), "{e}");
}

/// Labels each point by the sign of its height (a stand-in for a segmenter).
struct Ground;

impl ScanLabeller for Ground {
    fn identity(&self) -> String {
        "ground-by-height".into()
    }
    fn label(&self, scan: &Scan) -> veila_diffusion::Result<Vec<u32>> {
        Ok(scan
            .points
            .xyz
            .iter()
            .map(|p| if p.z < -1.0 { 40 } else { 0 })
            .collect())
    }
}

/// Gives one label too few.
struct Short;

impl ScanLabeller for Short {
    fn identity(&self) -> String {
        "short".into()
    }
    fn label(&self, scan: &Scan) -> veila_diffusion::Result<Vec<u32>> {
        Ok(vec![0; scan.points.len() - 1])
    }
}

#[test]
fn the_labeller_hook_writes_a_label_per_point_beside_each_scan() {
    let (bundle, tmp, kitti) = setup(2);
    let out = tmp.path().join("out");
    let plain = tmp.path().join("plain");
    let mut j = job(&bundle, &out, (0, 1));
    j.labeller = Some(&Ground);
    run(&bundle, &kitti, &j).unwrap();
    run(&bundle, &kitti, &job(&bundle, &plain, (0, 1))).unwrap();
    let f = files(&out);
    for id in ["000000", "000001"] {
        let bin = &f[&format!("velodyne/{id}.bin")];
        // the same scan as without labels
        assert_eq!(bin, &files(&plain)[&format!("velodyne/{id}.bin")]);
        let labels = &f[&format!("labels/{id}.label")];
        assert_eq!(labels.len(), bin.len() / 4);
        assert!(labels.chunks(4).any(|c| c == 40u32.to_le_bytes()));
    }
    let text = String::from_utf8(f[DATASET_MANIFEST].clone()).unwrap();
    assert!(
        text.contains("\"labeller\": \"ground-by-height\""),
        "{text}"
    );
    // a lost label file makes its frame incomplete: both files are written again, alike
    std::fs::remove_file(out.join("labels/000001.label")).unwrap();
    let s = run(&bundle, &kitti, &j).unwrap();
    assert_eq!((s.generated, s.skipped), (1, 1));
    assert_eq!(files(&out), f);
    // the labelled folder is another job than the plain one
    let e = run(&bundle, &kitti, &job(&bundle, &out, (0, 1))).unwrap_err();
    assert!(e.to_string().contains("labeller"), "{e}");
    // a labeller that miscounts: an error naming the frame, and no file of it
    let bad_out = tmp.path().join("bad");
    let mut bad = job(&bundle, &bad_out, (0, 1));
    bad.labeller = Some(&Short);
    let e = run(&bundle, &kitti, &bad).unwrap_err().to_string();
    assert!(e.contains("000000.png") && e.contains("labels for"), "{e}");
    let left: Vec<String> = files(&bad_out).into_keys().collect();
    assert_eq!(left, ["dataset.json"]);
}

#[test]
fn seeds_and_names_follow_their_rules() {
    // pinned: a change would silently change every generated dataset
    assert_eq!(frame_seed(0, "000000"), frame_seed(0, "000000"));
    assert_ne!(frame_seed(0, "000000"), frame_seed(0, "000001"));
    assert_ne!(frame_seed(0, "000000"), frame_seed(1, "000000"));
    let hex = veila_data::shard::sha256_hex(b"veila-frame-seed/1\n7\n08_000123");
    assert_eq!(
        frame_seed(7, "08_000123"),
        u64::from_str_radix(&hex[..16], 16).unwrap()
    );
    assert_eq!(frame_name("08/000123"), "08_000123");
    assert_eq!(frame_name("../a b.c"), "_._a_b.c");
    assert_eq!(frame_name("n015-2018-07-24"), "n015-2018-07-24");
    // two ids of one name are refused
    let tmp = tempfile::tempdir().unwrap();
    let dir: PathBuf = tmp.path().join("kitti");
    make_kitti(&dir, 1);
    std::fs::copy(
        dir.join("image_2/000000.png"),
        dir.join("image_2/000000.jpg"),
    )
    .unwrap();
    let e = FrameSource::open(&dir).unwrap_err().to_string();
    assert!(e.contains("000000.jpg") && e.contains("keep one"), "{e}");
    std::fs::remove_file(dir.join("image_2/000000.jpg")).unwrap();
    std::fs::remove_file(dir.join("calib/000000.txt")).unwrap();
    let e = FrameSource::open(&dir).unwrap_err().to_string();
    assert!(
        e.contains("000000.png") && e.contains("calib/000000.txt"),
        "{e}"
    );
}

/// `--segmenter`: the bundled segmenter as the labeller gives each written scan the labels
/// `veila segment predict` gives that `.bin` file, and names itself in `dataset.json`.
#[test]
fn the_bundled_segmenter_pseudo_labels_as_segment_predict_labels_the_written_scans() {
    use veila_diffusion::app::segment::SegmenterModel;
    let seg_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/segmenter");
    let seg = SegmenterModel::from_dir(&seg_dir, &Device::Cpu).unwrap();
    let (bundle, tmp, kitti) = setup(2);
    let out = tmp.path().join("out");
    let mut j = job(&bundle, &out, (0, 1));
    j.labeller = Some(&seg);
    run(&bundle, &kitti, &j).unwrap();
    let manifest = std::fs::read_to_string(out.join(DATASET_MANIFEST)).unwrap();
    assert!(
        seg.identity().starts_with("segmenter manifest sha256 ")
            && manifest.contains(seg.identity()),
        "{manifest}"
    );
    let mut labelled = 0usize;
    for id in ["000000", "000001"] {
        let cloud =
            veila_data::scan::read_kitti_bin_records(&out.join(format!("velodyne/{id}.bin")))
                .unwrap();
        let grid = seg.grid_scan(&cloud.xyz, &cloud.intensity).unwrap();
        let expect = seg.raw_ids(&seg.predict(std::slice::from_ref(&grid)).unwrap()[0]);
        let written: Vec<u32> = std::fs::read(out.join(format!("labels/{id}.label")))
            .unwrap()
            .chunks(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        assert_eq!(written.len(), cloud.xyz.len());
        assert_eq!(written, expect, "frame {id}");
        labelled += written.iter().filter(|&&l| l != 0).count();
    }
    assert!(labelled > 0, "every point unlabelled");
}
