//! The image encoders a model bundle can name, by kind: the project's [`SmallCnn`] and the
//! pretrained SegFormer (MiT), Depth-Anything-V2 and DINOv2 families, with their Hugging Face
//! weights.
//!
//! | kind | architecture | weights (`model.safetensors` of) |
//! |---|---|---|
//! | `small-cnn` | [`SmallCnn`], trained by this project | the bundle itself |
//! | `segformer-b0` .. `segformer-b5` | [`MitEncoder`] MiT-b0..b5 | `nvidia/segformer-bN-finetuned-cityscapes-1024-1024` (or `nvidia/mit-bN`) |
//! | `depth-anything-v2-{small,base,large}` | [`DepthAnythingV2Encoder`] | `depth-anything/Depth-Anything-V2-{Small,Base,Large}-hf` |
//! | `dinov2-{s,b,l}` | [`DinoV2Encoder`] | `facebook/dinov2-{small,base,large}` |
//!
//! [`EncoderKind::load_pretrained`] finds where the encoder sits in the file (SegFormer:
//! `segformer.encoder.` or `encoder.`; DINOv2: the root or a Depth-Anything file's `backbone.`),
//! then checks every tensor before building ([`super::load_checked_bytes`]): missing and mis-shaped
//! tensors are reported by name, with the file. [`AnyEncoder`] holds any of them behind the one
//! [`ImageEncoder`] interface, and [`AnyEncoder::encode_rgb8`] feeds it `u8` images through the
//! kind's [`ImageProcessor`] (a patch encoder gets the nearest size that is a multiple of its
//! patch, resampled as its reference processor does).
//!
//! ```
//! use veila_nn::encoders::kind::EncoderKind;
//!
//! let kind: EncoderKind = "depth-anything-v2-small".parse().unwrap();
//! assert_eq!(kind.channels(), Some([48, 96, 192, 384]));
//! assert_eq!(kind.hub_repo(), Some("depth-anything/Depth-Anything-V2-Small-hf"));
//! // a 96 x 320 camera image is fed as 98 x 322 (multiples of 14)
//! assert_eq!(kind.input_size(96, 320).unwrap(), (98, 322));
//! assert!("segformer-b6".parse::<EncoderKind>().is_err());
//! ```

use std::fmt;
use std::path::Path;
use std::str::FromStr;
use std::sync::Arc;

use candle_core::{DType, Device, Tensor};
use veila_geom::PinholeCamera;

use super::depth_anything::{DepthAnythingV2Config, DepthAnythingV2Encoder};
use super::dinov2::{DinoV2Config, DinoV2Encoder};
use super::mit::{MitConfig, MitEncoder};
use super::preprocess::{ImageProcessor, Resample, ResizeRule};
use super::small_cnn::SmallCnn;
use super::{ImageEncoder, Normalization, rgb8_to_tensor};

/// Size of a ViT family member.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum VitSize {
    /// ViT-S/14.
    Small,
    /// ViT-B/14.
    Base,
    /// ViT-L/14.
    Large,
}

/// An image encoder a bundle can name (see the [module docs](self)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum EncoderKind {
    /// The project's small CNN, trained with the bundle.
    SmallCnn,
    /// SegFormer's MiT-bN encoder, `N` in `0..=5`.
    SegFormer(u8),
    /// Depth-Anything-V2 (DINOv2 + DPT reassemble).
    DepthAnythingV2(VitSize),
    /// A plain DINOv2 backbone.
    DinoV2(VitSize),
}

impl EncoderKind {
    /// Every kind, in the order of the module docs' table.
    pub fn all() -> Vec<EncoderKind> {
        let mut v = vec![EncoderKind::SmallCnn];
        v.extend((0..=5).map(EncoderKind::SegFormer));
        for s in [VitSize::Small, VitSize::Base, VitSize::Large] {
            v.push(EncoderKind::DepthAnythingV2(s));
        }
        for s in [VitSize::Small, VitSize::Base, VitSize::Large] {
            v.push(EncoderKind::DinoV2(s));
        }
        v
    }

    /// Whether its weights come from outside the bundle.
    pub fn is_pretrained(self) -> bool {
        self != EncoderKind::SmallCnn
    }

    /// The Hugging Face repository whose `model.safetensors` holds the weights (`None` for the
    /// small CNN).
    pub fn hub_repo(self) -> Option<&'static str> {
        Some(match self {
            EncoderKind::SmallCnn => return None,
            EncoderKind::SegFormer(0) => "nvidia/segformer-b0-finetuned-cityscapes-1024-1024",
            EncoderKind::SegFormer(1) => "nvidia/segformer-b1-finetuned-cityscapes-1024-1024",
            EncoderKind::SegFormer(2) => "nvidia/segformer-b2-finetuned-cityscapes-1024-1024",
            EncoderKind::SegFormer(3) => "nvidia/segformer-b3-finetuned-cityscapes-1024-1024",
            EncoderKind::SegFormer(4) => "nvidia/segformer-b4-finetuned-cityscapes-1024-1024",
            EncoderKind::SegFormer(_) => "nvidia/segformer-b5-finetuned-cityscapes-1024-1024",
            EncoderKind::DepthAnythingV2(VitSize::Small) => {
                "depth-anything/Depth-Anything-V2-Small-hf"
            }
            EncoderKind::DepthAnythingV2(VitSize::Base) => {
                "depth-anything/Depth-Anything-V2-Base-hf"
            }
            EncoderKind::DepthAnythingV2(VitSize::Large) => {
                "depth-anything/Depth-Anything-V2-Large-hf"
            }
            EncoderKind::DinoV2(VitSize::Small) => "facebook/dinov2-small",
            EncoderKind::DinoV2(VitSize::Base) => "facebook/dinov2-base",
            EncoderKind::DinoV2(VitSize::Large) => "facebook/dinov2-large",
        })
    }

    /// The MiT config of a `segformer-bN` kind.
    pub fn mit_config(self) -> Option<MitConfig> {
        self.mit()
    }

    /// The full SegFormer (MiT + decode head) of a `segformer-bN` kind as the Cityscapes
    /// checkpoints have it: 19 classes, head width 256 for b0 / b1 and 768 for b2..b5.
    pub fn segformer_cityscapes_config(self) -> Option<super::mit::SegFormerConfig> {
        let EncoderKind::SegFormer(n) = self else {
            return None;
        };
        Some(super::mit::SegFormerConfig {
            encoder: self.mit()?,
            decoder_hidden_size: if n <= 1 { 256 } else { 768 },
            ..super::mit::SegFormerConfig::b0_cityscapes()
        })
    }

    /// The Depth-Anything-V2 config of a `depth-anything-v2-*` kind (relative depth, as the `-hf`
    /// checkpoints).
    pub fn depth_anything_config(self) -> Option<DepthAnythingV2Config> {
        self.depth_anything()
    }

    /// The DINOv2 config of a `dinov2-*` kind.
    pub fn dinov2_config(self) -> Option<DinoV2Config> {
        self.dinov2()
    }

    fn mit(self) -> Option<MitConfig> {
        match self {
            EncoderKind::SegFormer(n) => Some(match n {
                0 => MitConfig::mit_b0(),
                1 => MitConfig::mit_b1(),
                2 => MitConfig::mit_b2(),
                3 => MitConfig::mit_b3(),
                4 => MitConfig::mit_b4(),
                _ => MitConfig::mit_b5(),
            }),
            _ => None,
        }
    }

    fn depth_anything(self) -> Option<DepthAnythingV2Config> {
        match self {
            EncoderKind::DepthAnythingV2(VitSize::Small) => Some(DepthAnythingV2Config::small()),
            EncoderKind::DepthAnythingV2(VitSize::Base) => Some(DepthAnythingV2Config::base()),
            EncoderKind::DepthAnythingV2(VitSize::Large) => Some(DepthAnythingV2Config::large()),
            _ => None,
        }
    }

    fn dinov2(self) -> Option<DinoV2Config> {
        match self {
            EncoderKind::DinoV2(VitSize::Small) => Some(DinoV2Config::vit_small_14()),
            EncoderKind::DinoV2(VitSize::Base) => Some(DinoV2Config::vit_base_14()),
            EncoderKind::DinoV2(VitSize::Large) => Some(DinoV2Config::vit_large_14()),
            _ => None,
        }
    }

    /// Output channels of a pretrained kind (`None` for the small CNN, whose config says).
    pub fn channels(self) -> Option<[usize; 4]> {
        if let Some(c) = self.mit() {
            return Some(c.hidden_sizes);
        }
        if let Some(c) = self.depth_anything() {
            return Some(c.neck_hidden_sizes);
        }
        self.dinov2().map(|c| [c.hidden_size; 4])
    }

    /// How a bundle fits its camera image to this encoder: unchanged when the sides are
    /// multiples of the encoder's patch or stride product (14 for the ViTs, 32 for MiT),
    /// otherwise resized to the nearest such size with the reference processor's filter
    /// (bicubic for the ViTs, bilinear for SegFormer). The small CNN takes any size.
    pub fn processor(self) -> ImageProcessor {
        let (multiple, resample) = match self {
            EncoderKind::SmallCnn => (1, Resample::Bilinear),
            EncoderKind::SegFormer(_) => (32, Resample::Bilinear),
            EncoderKind::DepthAnythingV2(_) | EncoderKind::DinoV2(_) => (14, Resample::Bicubic),
        };
        ImageProcessor {
            resize: if multiple == 1 {
                ResizeRule::Keep
            } else {
                ResizeRule::NearestMultiple { multiple }
            },
            resample,
            normalization: Normalization::IMAGENET,
        }
    }

    /// The size a `height x width` camera image is fed at ([`Self::processor`]).
    pub fn input_size(self, height: usize, width: usize) -> crate::Result<(usize, usize)> {
        self.processor().output_size(height, width)
    }

    /// Feature map sizes of a pretrained kind for a `height x width` camera image (after
    /// [`Self::input_size`]); `None` for the small CNN.
    pub fn feature_sizes(
        self,
        height: usize,
        width: usize,
    ) -> crate::Result<Option<[(usize, usize); 4]>> {
        if !self.is_pretrained() {
            return Ok(None);
        }
        let (h, w) = self.input_size(height, width)?;
        Ok(Some(if let Some(c) = self.mit() {
            c.feature_sizes(h, w)
        } else if let Some(c) = self.depth_anything() {
            c.feature_sizes(h, w)
        } else {
            let p = 14;
            [(h / p, w / p); 4]
        }))
    }

    /// Builds a pretrained encoder from the bytes of its safetensors file (`path` names it in
    /// errors), after checking every tensor the encoder reads.
    ///
    /// # Errors
    /// [`crate::Error::Config`] for [`EncoderKind::SmallCnn`] (its config lives in the bundle)
    /// and for files that hold no encoder of this family; [`crate::Error::CheckpointMismatch`]
    /// naming the missing and mis-shaped tensors (a file of another size, say).
    pub fn load_pretrained(
        self,
        bytes: &[u8],
        path: &Path,
        dtype: DType,
        device: &Device,
    ) -> crate::Result<AnyEncoder> {
        let names = tensor_names(bytes, path)?;
        let has = |n: &str| names.iter().any(|x| x == n);
        let not_this = |want: &str| {
            crate::Error::Config(format!(
                "{}: not a {self} checkpoint (no tensor `{want}`); expected `model.safetensors` of {}",
                path.display(),
                self.hub_repo().unwrap_or("-")
            ))
        };
        if let Some(mut cfg) = self.mit() {
            const PROBE: &str = "patch_embeddings.0.proj.weight";
            cfg.weight_prefix = ["segformer.encoder", "encoder", ""]
                .into_iter()
                .find(|p| has(&scoped(p, PROBE)))
                .ok_or_else(|| not_this(&scoped("segformer.encoder", PROBE)))?
                .to_string();
            let scope = scoped(&cfg.weight_prefix, "");
            let enc = super::load_checked_bytes(
                bytes,
                path,
                dtype,
                device,
                |n| n.starts_with(&scope),
                |vb| MitEncoder::new(&cfg, vb),
            )?;
            return Ok(AnyEncoder::SegFormer(self, Arc::new(enc)));
        }
        if let Some(cfg) = self.depth_anything() {
            const PROBE: &str = "backbone.embeddings.cls_token";
            if !has(PROBE) {
                return Err(not_this(PROBE));
            }
            let enc = super::load_checked_bytes(
                bytes,
                path,
                dtype,
                device,
                |n| {
                    (n.starts_with("backbone.") || n.starts_with("neck.reassemble_stage."))
                        && !n.ends_with("mask_token")
                },
                |vb| DepthAnythingV2Encoder::new(&cfg, vb),
            )?;
            return Ok(AnyEncoder::DepthAnythingV2(self, Arc::new(enc)));
        }
        if let Some(cfg) = self.dinov2() {
            const PROBE: &str = "embeddings.cls_token";
            let prefix = ["", "backbone", "dinov2"]
                .into_iter()
                .find(|p| has(&scoped(p, PROBE)))
                .ok_or_else(|| not_this(PROBE))?;
            let scope = scoped(prefix, "");
            let out = DinoV2Encoder::default_out_indices(&cfg);
            let enc = super::load_checked_bytes(
                bytes,
                path,
                dtype,
                device,
                |n| {
                    n.starts_with(&scope)
                        && (n.starts_with(&scoped(prefix, "embeddings."))
                            || n.starts_with(&scoped(prefix, "encoder."))
                            || n.starts_with(&scoped(prefix, "layernorm.")))
                        && !n.ends_with("mask_token")
                },
                |vb| {
                    let vb = if prefix.is_empty() { vb } else { vb.pp(prefix) };
                    DinoV2Encoder::new(&cfg, out, vb)
                },
            )?;
            return Ok(AnyEncoder::DinoV2(self, Arc::new(enc)));
        }
        Err(crate::Error::Config(format!(
            "{self}: its weights live in the bundle, not in a pretrained file"
        )))
    }
}

fn scoped(prefix: &str, name: &str) -> String {
    if prefix.is_empty() {
        name.to_string()
    } else {
        format!("{prefix}.{name}")
    }
}

/// The tensor names of a safetensors file (its header only).
fn tensor_names(bytes: &[u8], path: &Path) -> crate::Result<Vec<String>> {
    let (_, meta) = safetensors::SafeTensors::read_metadata(bytes).map_err(|e| {
        crate::Error::Config(format!("{}: not a safetensors file: {e}", path.display()))
    })?;
    Ok(meta.tensors().into_keys().collect())
}

impl fmt::Display for EncoderKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let size = |s: &VitSize, long: bool| match (s, long) {
            (VitSize::Small, true) => "small",
            (VitSize::Base, true) => "base",
            (VitSize::Large, true) => "large",
            (VitSize::Small, false) => "s",
            (VitSize::Base, false) => "b",
            (VitSize::Large, false) => "l",
        };
        match self {
            EncoderKind::SmallCnn => f.write_str("small-cnn"),
            EncoderKind::SegFormer(n) => write!(f, "segformer-b{n}"),
            EncoderKind::DepthAnythingV2(s) => write!(f, "depth-anything-v2-{}", size(s, true)),
            EncoderKind::DinoV2(s) => write!(f, "dinov2-{}", size(s, false)),
        }
    }
}

impl FromStr for EncoderKind {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        EncoderKind::all()
            .into_iter()
            .find(|k| k.to_string() == s)
            .ok_or_else(|| {
                let names: Vec<String> = EncoderKind::all().iter().map(|k| k.to_string()).collect();
                format!("unknown encoder `{s}`; one of: {}", names.join(", "))
            })
    }
}

impl serde::Serialize for EncoderKind {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> serde::Deserialize<'de> for EncoderKind {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

/// Any encoder of [`EncoderKind`], behind the one [`ImageEncoder`] interface (cheap to clone).
#[derive(Debug, Clone)]
pub enum AnyEncoder {
    /// The small CNN.
    SmallCnn(Arc<SmallCnn>),
    /// A SegFormer MiT encoder.
    SegFormer(EncoderKind, Arc<MitEncoder>),
    /// A Depth-Anything-V2 encoder.
    DepthAnythingV2(EncoderKind, Arc<DepthAnythingV2Encoder>),
    /// A DINOv2 backbone.
    DinoV2(EncoderKind, Arc<DinoV2Encoder>),
}

impl From<SmallCnn> for AnyEncoder {
    fn from(net: SmallCnn) -> Self {
        AnyEncoder::SmallCnn(Arc::new(net))
    }
}

impl AnyEncoder {
    /// Its kind.
    pub fn kind(&self) -> EncoderKind {
        match self {
            AnyEncoder::SmallCnn(_) => EncoderKind::SmallCnn,
            AnyEncoder::SegFormer(k, _)
            | AnyEncoder::DepthAnythingV2(k, _)
            | AnyEncoder::DinoV2(k, _) => *k,
        }
    }

    /// The small CNN, when it is one (its dense heads predict depth and class maps).
    pub fn as_small_cnn(&self) -> Option<&SmallCnn> {
        match self {
            AnyEncoder::SmallCnn(n) => Some(n.as_ref()),
            _ => None,
        }
    }

    fn inner(&self) -> &dyn ImageEncoder {
        match self {
            AnyEncoder::SmallCnn(n) => n.as_ref(),
            AnyEncoder::SegFormer(_, e) => e.as_ref(),
            AnyEncoder::DepthAnythingV2(_, e) => e.as_ref(),
            AnyEncoder::DinoV2(_, e) => e.as_ref(),
        }
    }

    /// Feature sizes for a `height x width` camera image, after the kind's input fitting.
    pub fn feature_sizes_for_image(
        &self,
        height: usize,
        width: usize,
    ) -> crate::Result<[(usize, usize); 4]> {
        let (h, w) = self.kind().input_size(height, width)?;
        Ok(self.inner().feature_sizes(h, w))
    }

    /// Encodes camera images (each `height x width x 3` RGB bytes) as one batch, each fitted to
    /// the encoder by its kind's [`ImageProcessor`] first. An error for a small CNN that takes
    /// the ground prior, which needs the cameras ([`Self::encode_rgb8_with_cameras`]).
    pub fn encode_rgb8(
        &self,
        images: &[&[u8]],
        height: usize,
        width: usize,
        device: &Device,
    ) -> crate::Result<Vec<Tensor>> {
        self.encode_rgb8_with_cameras(images, None, height, width, device)
    }

    /// Whether the encoder needs each image's camera (a small CNN with the ground prior).
    pub fn needs_cameras(&self) -> bool {
        self.as_small_cnn()
            .is_some_and(|n| n.config().ground_prior.is_some())
    }

    /// [`Self::encode_rgb8`] with each image's camera (`cameras[i]` of `images[i]`, the camera of
    /// the `height x width` image): a small CNN with the ground prior gets its channel computed
    /// from that camera; the other encoders ignore the cameras.
    ///
    /// # Errors
    /// Besides [`Self::encode_rgb8`]'s: a camera count other than the image count, or no
    /// cameras for an encoder that needs them.
    pub fn encode_rgb8_with_cameras(
        &self,
        images: &[&[u8]],
        cameras: Option<&[PinholeCamera]>,
        height: usize,
        width: usize,
        device: &Device,
    ) -> crate::Result<Vec<Tensor>> {
        if let Some(c) = cameras
            && c.len() != images.len()
        {
            input_bail!(
                "AnyEncoder::encode_rgb8_with_cameras: {} images but {} cameras",
                images.len(),
                c.len()
            );
        }
        let p = self.kind().processor();
        let small = self.as_small_cnn().map(|n| n.config());
        let batch = images
            .iter()
            .enumerate()
            .map(|(i, rgb)| {
                let (bytes, h, w) = p.resize_rgb8(rgb, height, width)?;
                match small {
                    Some(cfg) if cfg.ground_prior.is_some() => {
                        cfg.input_tensor(&bytes, h, w, cameras.map(|c| &c[i]), device)
                    }
                    _ => rgb8_to_tensor(&bytes, h, w, &p.normalization, device),
                }
            })
            .collect::<crate::Result<Vec<_>>>()?;
        if batch.is_empty() {
            input_bail!("AnyEncoder::encode_rgb8: no images");
        }
        self.forward(&Tensor::cat(&batch, 0)?)
    }
}

forward_image_encoder!([] AnyEncoder, |s| s.inner());

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_are_unique() {
        let all = EncoderKind::all();
        assert_eq!(all.len(), 1 + 6 + 3 + 3);
        let names: std::collections::BTreeSet<String> = all.iter().map(|k| k.to_string()).collect();
        assert_eq!(names.len(), all.len());
        for k in all {
            assert_eq!(k.to_string().parse::<EncoderKind>().unwrap(), k);
            let json = serde_json::to_string(&k).unwrap();
            assert_eq!(serde_json::from_str::<EncoderKind>(&json).unwrap(), k);
            assert_eq!(k.hub_repo().is_some(), k.is_pretrained());
        }
        let e = "depth-anything-v3".parse::<EncoderKind>().unwrap_err();
        assert!(e.contains("depth-anything-v2-small"), "{e}");
    }

    #[test]
    fn input_specs_agree_with_the_kinds() {
        // the fitted size satisfies each architecture's own input spec
        assert_eq!(
            EncoderKind::SegFormer(0).input_size(96, 320).unwrap(),
            (96, 320)
        );
        assert_eq!(
            EncoderKind::SegFormer(0).input_size(100, 300).unwrap(),
            (96, 288)
        );
        assert_eq!(
            EncoderKind::DinoV2(VitSize::Large)
                .input_size(96, 320)
                .unwrap(),
            (98, 322)
        );
        assert_eq!(EncoderKind::SmallCnn.input_size(37, 41).unwrap(), (37, 41));
        assert_eq!(
            EncoderKind::DinoV2(VitSize::Base)
                .feature_sizes(98, 322)
                .unwrap(),
            Some([(7, 23); 4])
        );
        assert_eq!(
            EncoderKind::DepthAnythingV2(VitSize::Large).channels(),
            Some([256, 512, 1024, 1024])
        );
    }
}
