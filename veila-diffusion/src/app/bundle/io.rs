//! Bundle IO: reading a bundle folder (or its files from memory), verifying every file against
//! the manifest before it is parsed, and saving a bundle folder atomically.

use std::collections::{BTreeMap, HashMap};
use std::fs;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};
use veila_data::contained::contained;
use veila_data::read_capped::{MAX_JSON_METADATA_BYTES, read_metadata};
use veila_nn::Denoiser as Net;
use veila_nn::encoders::kind::AnyEncoder;
use veila_nn::encoders::small_cnn::SmallCnn;

use super::{
    BUNDLE_FORMAT, BundleConfig, CONFIG_FILE, DENOISER_FILE, DEPTH_FILE, EncoderSpec,
    MANIFEST_FILE, MANIFEST_FORMAT, MEAN_FILE, SEMANTIC_FILE, safetensors_bytes, sha256_hex,
};
use crate::error::{Error, Result};

/// `manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// [`MANIFEST_FORMAT`].
    pub format: String,
    /// File name → lowercase hex sha256.
    pub files: BTreeMap<String, String>,
}

impl Manifest {
    /// Parses the bytes of a `manifest.json` (`path` names it in errors) and checks its format
    /// ([`MANIFEST_FORMAT`]).
    pub fn parse(bytes: &[u8], path: &Path) -> Result<Self> {
        let manifest: Manifest = serde_json::from_slice(bytes).map_err(|source| Error::Json {
            path: path.to_path_buf(),
            source,
        })?;
        if manifest.format != MANIFEST_FORMAT {
            return Err(Error::Checkpoint {
                reason: format!(
                    "manifest format `{}`, expected `{MANIFEST_FORMAT}`",
                    manifest.format
                ),
                path: path.to_path_buf(),
            });
        }
        Ok(manifest)
    }

    /// `bytes`, the content of file `name` of the folder `origin`, when the manifest lists it with
    /// their sha256; otherwise an error naming the file (or the manifest).
    pub fn verify<'a>(&self, name: &str, bytes: &'a [u8], origin: &Path) -> Result<&'a [u8]> {
        let want = self.files.get(name).ok_or_else(|| Error::Checkpoint {
            reason: format!("`{name}` is not listed in the manifest"),
            path: origin.join(MANIFEST_FILE),
        })?;
        let got = sha256_hex(bytes);
        if !want.eq_ignore_ascii_case(&got) {
            return Err(Error::Checkpoint {
                reason: format!(
                    "sha256 mismatch: the manifest says {want}, the file hashes to {got} (corrupted or replaced)"
                ),
                path: origin.join(name),
            });
        }
        Ok(bytes)
    }
}

/// The bytes of file `name` of the model folder `dir` (`what` names the kind of folder in errors:
/// `bundle`, `segmenter`): it must lie inside `dir` after links are followed
/// ([`veila_data::contained::contained`]; one that leads out is refused unread) and be a regular
/// file under its kind's cap, checked before it is read: weights (`.safetensors`) under
/// `veila-nn`'s, JSON under [`MAX_JSON_METADATA_BYTES`].
pub(crate) fn read_folder_file(dir: &Path, name: &str, what: &str) -> Result<Vec<u8>> {
    let path = contained(dir, Path::new(name), &format!("{what} file"), dir)?;
    if name.ends_with(".safetensors") {
        Ok(veila_nn::checkpoint::read_weights_file(&path)?)
    } else {
        Ok(read_metadata(
            &path,
            MAX_JSON_METADATA_BYTES,
            &format!("a {what}'s {name}"),
        )?)
    }
}

/// A model folder's files in memory (`(file name, bytes)`) with their manifest, already parsed:
/// [`ModelFiles::verified`] gives a file's bytes once the manifest vouches for them.
#[derive(Debug)]
pub(crate) struct ModelFiles<'a> {
    files: &'a [(&'a str, &'a [u8])],
    origin: &'a Path,
    manifest: Manifest,
}

impl<'a> ModelFiles<'a> {
    /// Parses the manifest among `files` (`origin` names the folder in errors).
    pub(crate) fn new(files: &'a [(&'a str, &'a [u8])], origin: &'a Path) -> Result<Self> {
        let mut me = ModelFiles {
            files,
            origin,
            manifest: Manifest {
                format: String::new(),
                files: BTreeMap::new(),
            },
        };
        me.manifest = Manifest::parse(me.get(MANIFEST_FILE)?, &origin.join(MANIFEST_FILE))?;
        Ok(me)
    }

    fn get(&self, name: &str) -> Result<&'a [u8]> {
        self.files
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, b)| *b)
            .ok_or_else(|| Error::Checkpoint {
                reason: format!("missing file `{name}`"),
                path: self.origin.to_path_buf(),
            })
    }

    /// The bytes of `manifest.json` (its SHA-256 identifies the folder: every file is checked
    /// against it).
    pub(crate) fn manifest_bytes(&self) -> Result<&'a [u8]> {
        self.get(MANIFEST_FILE)
    }

    /// The bytes of file `name`, listed in the manifest with their sha256 ([`Manifest::verify`]);
    /// otherwise an error naming the file.
    pub(crate) fn verified(&self, name: &str) -> Result<&'a [u8]> {
        self.manifest.verify(name, self.get(name)?, self.origin)
    }
}

/// A model folder being written (a bundle, a segmenter): its files go into a hidden temporary
/// folder beside it, each listed with its sha256 in the manifest, which [`ManifestFolder::finish`]
/// writes last before one rename puts the folder in place (an existing one is replaced only after
/// the new one is complete).
#[derive(Debug)]
pub(crate) struct ManifestFolder {
    dir: PathBuf,
    parent: PathBuf,
    name: String,
    tmp: PathBuf,
    manifest: Manifest,
}

fn folder_io(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> Error {
    let path = path.to_path_buf();
    move |source| Error::Io {
        action,
        path,
        source,
    }
}

impl ManifestFolder {
    /// Starts writing the folder `dir` (its parent is created).
    pub(crate) fn new(dir: &Path) -> Result<Self> {
        let parent = dir
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_path_buf();
        fs::create_dir_all(&parent).map_err(folder_io("creating model parent folder", &parent))?;
        let name = dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "model".into());
        let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
        let _ = fs::remove_dir_all(&tmp);
        fs::create_dir_all(&tmp).map_err(folder_io("creating model folder", &tmp))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            parent,
            name,
            tmp,
            manifest: Manifest {
                format: MANIFEST_FORMAT.into(),
                files: BTreeMap::new(),
            },
        })
    }

    /// The temporary folder (for files the manifest does not list).
    pub(crate) fn tmp(&self) -> &Path {
        &self.tmp
    }

    /// Writes `file` and lists it in the manifest.
    pub(crate) fn put(&mut self, file: &str, bytes: &[u8]) -> Result<()> {
        let p = self.tmp.join(file);
        fs::write(&p, bytes).map_err(folder_io("writing model file", &p))?;
        self.manifest.files.insert(file.into(), sha256_hex(bytes));
        Ok(())
    }

    /// Writes the manifest and renames the folder into place.
    pub(crate) fn finish(self) -> Result<()> {
        let json = serde_json::to_vec_pretty(&self.manifest).map_err(|source| Error::Json {
            path: self.dir.join(MANIFEST_FILE),
            source,
        })?;
        let p = self.tmp.join(MANIFEST_FILE);
        fs::write(&p, json).map_err(folder_io("writing model file", &p))?;
        let dir = &self.dir;
        if dir.exists() {
            let old = self
                .parent
                .join(format!(".{}.old-{}", self.name, std::process::id()));
            let _ = fs::remove_dir_all(&old);
            fs::rename(dir, &old).map_err(folder_io("replacing model folder", dir))?;
            fs::rename(&self.tmp, dir).map_err(folder_io("replacing model folder", dir))?;
            let _ = fs::remove_dir_all(&old);
        } else {
            fs::rename(&self.tmp, dir).map_err(folder_io("writing model folder", dir))?;
        }
        Ok(())
    }
}

/// A loaded bundle: config, networks (on one device, `f32`).
#[derive(Debug, Clone)]
pub struct Bundle {
    /// The config.
    pub config: BundleConfig,
    /// `E_s`.
    pub semantic: Option<AnyEncoder>,
    /// `E_d`.
    pub depth: Option<AnyEncoder>,
    /// The denoiser.
    pub denoiser: Net,
    /// The denoiser's weights by name (to rebuild it for another number of views).
    pub weights: HashMap<String, Tensor>,
    /// The mean network (residual diffusion's or a prior's) and its weights by name.
    pub mean: Option<(Net, HashMap<String, Tensor>)>,
    /// Where it was loaded from (a folder, or a label for embedded bundles).
    pub origin: PathBuf,
    /// Lowercase hex SHA-256 of its `manifest.json`: the bundle's identity, since every file it
    /// loads was checked against that manifest (a run that must use the same model records it).
    pub manifest_sha256: String,
}

impl Bundle {
    /// Reads and verifies a bundle folder. Its `manifest.json` and `bundle.json` must be regular
    /// files of at most [`MAX_JSON_METADATA_BYTES`] (checked before they are read). Every file it
    /// reads, pretrained weights included, lies inside `dir` after links are followed
    /// ([`veila_data::contained::contained`]): one that leads out is refused unread.
    pub fn from_dir(dir: &Path, device: &Device) -> Result<Self> {
        let read = |name: &str| read_folder_file(dir, name, "bundle");
        let manifest = read(MANIFEST_FILE)?;
        let config = read(CONFIG_FILE)?;
        let cfg: BundleConfig = serde_json::from_slice(&config).map_err(|source| Error::Json {
            path: dir.join(CONFIG_FILE),
            source,
        })?;
        let mut files: Vec<(String, Vec<u8>)> = vec![
            (MANIFEST_FILE.into(), manifest),
            (CONFIG_FILE.into(), config),
        ];
        for name in cfg.weight_files() {
            files.push((name.into(), read(name)?));
        }
        let refs: Vec<(&str, &[u8])> = files
            .iter()
            .map(|(n, b)| (n.as_str(), b.as_slice()))
            .collect();
        Self::from_files(&refs, dir, device)
    }

    /// Builds a bundle from its files in memory (`(file name, bytes)`); `origin` names the source in
    /// errors. Every file is checked against `manifest.json` first.
    pub fn from_files(files: &[(&str, &[u8])], origin: &Path, device: &Device) -> Result<Self> {
        let model_files = ModelFiles::new(files, origin)?;
        let verified = |name: &str| model_files.verified(name);
        let cfg: BundleConfig =
            serde_json::from_slice(verified(CONFIG_FILE)?).map_err(|source| Error::Json {
                path: origin.join(CONFIG_FILE),
                source,
            })?;
        cfg.check(origin)?;
        let load_encoder = |spec: &EncoderSpec, field: &str, name: &str| -> Result<AnyEncoder> {
            match &spec.config {
                Some(c) if !spec.kind.is_pretrained() => {
                    let bytes = verified(name)?;
                    Ok(AnyEncoder::from(veila_nn::encoders::load_checked_bytes(
                        bytes,
                        &origin.join(name),
                        DType::F32,
                        device,
                        |_| true,
                        |vb| SmallCnn::new(c, vb),
                    )?))
                }
                _ => spec.load(origin, field, device),
            }
        };
        let semantic = cfg
            .semantic_encoder
            .as_ref()
            .map(|c| load_encoder(c, "semantic_encoder", SEMANTIC_FILE))
            .transpose()?;
        let depth = cfg
            .depth_encoder
            .as_ref()
            .map(|c| load_encoder(c, "depth_encoder", DEPTH_FILE))
            .transpose()?;
        let path = origin.join(DENOISER_FILE);
        let expected = veila_nn::checkpoint::expected_tensors(&cfg.denoiser)?;
        let weights = veila_nn::checkpoint::read_checked_bytes(
            verified(DENOISER_FILE)?,
            &path,
            &expected,
            device,
        )?;
        let denoiser = Net::new(
            &cfg.denoiser,
            candle_nn::VarBuilder::from_tensors(weights.clone(), DType::F32, device),
        )?;
        let mean = match cfg.mean_net() {
            Some(mean_net) => {
                let path = origin.join(MEAN_FILE);
                let expected = veila_nn::checkpoint::expected_tensors(mean_net)?;
                let w = veila_nn::checkpoint::read_checked_bytes(
                    verified(MEAN_FILE)?,
                    &path,
                    &expected,
                    device,
                )?;
                let net = Net::new(
                    mean_net,
                    candle_nn::VarBuilder::from_tensors(w.clone(), DType::F32, device),
                )?;
                Some((net, w))
            }
            None => None,
        };
        Ok(Self {
            config: cfg,
            semantic,
            depth,
            denoiser,
            weights,
            mean,
            origin: origin.to_path_buf(),
            manifest_sha256: sha256_hex(model_files.manifest_bytes()?),
        })
    }

    /// Writes a bundle folder: every file into a hidden temporary folder beside `dir`, the manifest
    /// last, then one rename (an existing `dir` is replaced only after the new one is complete).
    /// `weights` maps each of [`BundleConfig::weight_files`] to its tensors. A pretrained encoder
    /// whose `weights` is an absolute path (a file the caller chose) is put into the bundle as
    /// `FIELD.KIND.safetensors` (a hard link where the file system allows, else a copy), and
    /// `bundle.json` names it there: a bundle names no file outside itself.
    pub fn save(
        dir: &Path,
        config: &BundleConfig,
        weights: &HashMap<&str, HashMap<String, Tensor>>,
    ) -> Result<()> {
        config.check(dir)?;
        let mut folder = ManifestFolder::new(dir)?;
        let mut config = BundleConfig {
            format: BUNDLE_FORMAT.into(),
            ..config.clone()
        };
        // pretrained weights the caller gave by an absolute path (a training config's) come into
        // the bundle, which then names no file outside itself
        for (field, spec) in [
            ("semantic_encoder", &mut config.semantic_encoder),
            ("depth_encoder", &mut config.depth_encoder),
        ] {
            let Some(spec) = spec.as_mut().filter(|s| s.kind.is_pretrained()) else {
                continue;
            };
            let Some(src) = spec.weights.clone().filter(|w| w.is_absolute()) else {
                continue;
            };
            let file = format!("{field}.{}.safetensors", spec.kind);
            let dst = folder.tmp().join(&file);
            fs::hard_link(&src, &dst)
                .or_else(|_| fs::copy(&src, &dst).map(|_| ()))
                .map_err(folder_io(
                    "copying pretrained encoder weights into the bundle",
                    &src,
                ))?;
            spec.weights = Some(file.into());
        }
        let config = &config;
        let json = serde_json::to_vec_pretty(config).map_err(|source| Error::Json {
            path: dir.join(CONFIG_FILE),
            source,
        })?;
        folder.put(CONFIG_FILE, &json)?;
        for file in config.weight_files() {
            let tensors = weights.get(file).ok_or_else(|| Error::Checkpoint {
                reason: format!("no weights given for `{file}`"),
                path: dir.to_path_buf(),
            })?;
            let bytes = safetensors_bytes(tensors, &dir.join(file))?;
            folder.put(file, &bytes)?;
        }
        folder.finish()
    }
}

/// What generation needs of a bundle (the generation methods themselves, [`Bundle::generate`],
/// [`Bundle::inpaint`], [`Bundle::encode_views`], are in [`crate::app::generate`], which uses this module
/// and not the other way round).
impl Bundle {
    /// The range-image grid `(rows, cols)`.
    pub fn grid(&self) -> (usize, usize) {
        (self.config.denoiser.height(), self.config.denoiser.width())
    }

    /// Whether the denoiser uses the image.
    pub fn is_conditional(&self) -> bool {
        self.config.denoiser.conditioning.is_some()
    }

    pub(crate) fn denoiser_device(&self) -> &Device {
        self.denoiser
            .ray_features()
            .map(|t| t.device())
            .unwrap_or(&Device::Cpu)
    }

    /// The denoiser for `views` camera views (a model trained with one view runs on several: no
    /// weight depends on the number of views).
    pub(crate) fn net_for_views(&self, views: usize) -> Result<Net> {
        rebuild_for_views(
            &self.denoiser,
            &self.config.denoiser,
            &self.weights,
            views,
            self.denoiser_device(),
        )
    }

    /// The mean network (a residual bundle's or a prior's) for `views` camera views.
    pub(crate) fn mean_for_views(&self, views: usize) -> Result<Option<Net>> {
        match (&self.mean, self.config.mean_net()) {
            (Some((net, weights)), Some(mean_net)) => Ok(Some(rebuild_for_views(
                net,
                mean_net,
                weights,
                views,
                self.denoiser_device(),
            )?)),
            _ => Ok(None),
        }
    }
}

fn rebuild_for_views(
    net: &Net,
    cfg: &veila_nn::DenoiserConfig,
    weights: &HashMap<String, Tensor>,
    views: usize,
    device: &Device,
) -> Result<Net> {
    let Some(cc) = &cfg.conditioning else {
        return Ok(net.clone());
    };
    if cc.num_views == views {
        return Ok(net.clone());
    }
    let mut cfg = cfg.clone();
    if let Some(c) = cfg.conditioning.as_mut() {
        c.num_views = views;
    }
    Ok(Net::new(
        &cfg,
        VarBuilder::from_tensors(weights.clone(), DType::F32, device),
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bundle folder whose `bundle.json` is `make(path)` (its manifest a small placeholder:
    /// the files are refused before anything is parsed).
    fn bundle_dir_with_config(make: impl FnOnce(&Path)) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join(MANIFEST_FILE), b"{}").unwrap();
        make(&dir.path().join(CONFIG_FILE));
        dir
    }

    #[cfg(unix)]
    #[test]
    fn a_bundle_json_linked_to_dev_zero_is_refused_naming_it() {
        let dir = bundle_dir_with_config(|p| std::os::unix::fs::symlink("/dev/zero", p).unwrap());
        let e = Bundle::from_dir(dir.path(), &Device::Cpu)
            .unwrap_err()
            .to_string();
        // a link out of the bundle folder is refused before the size and type checks look at it
        assert!(
            e.contains(CONFIG_FILE) && e.contains("leads through the link `bundle.json`"),
            "{e}"
        );
    }

    #[test]
    fn a_sparse_3_gb_bundle_json_is_refused_unread() {
        let dir = bundle_dir_with_config(|p| {
            fs::File::create(p).unwrap().set_len(3 << 30).unwrap();
        });
        let e = Bundle::from_dir(dir.path(), &Device::Cpu)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(CONFIG_FILE)
                && e.contains(&format!(
                    "3221225472 bytes, more than the cap of {MAX_JSON_METADATA_BYTES} bytes"
                )),
            "{e}"
        );
    }
}
