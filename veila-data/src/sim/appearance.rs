//! Appearance randomisation of the camera image: a per-scene draw of sun, sky, class palettes and
//! texture styles ([`Appearance::draw`]), and the albedo of a surface point with its procedural
//! texture ([`Appearance::albedo`]).
//!
//! Everything is a pure function of (scene seed, configuration, point): the draw uses a `ChaCha8Rng`
//! seeded from the scene seed, the textures hash lattice points of world coordinates (so they stick
//! to surfaces when the camera moves) and never depend on the order or the thread rays are traced
//! in. Geometry, classes, instances and LiDAR reflectivities are never touched: only the camera's
//! albedo and lighting change.
//!
//! Textures are band-limited to the pixel footprint: a noise octave whose wavelength is below two
//! footprints fades to its mean, and joint lines thinner than a footprint spread into their
//! average coverage, so distant surfaces turn smooth instead of into per-pixel noise.

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::config::{AppearanceConfig, LightingConfig};
use super::hash::splitmix;
use super::material::{Material, stock};
use super::mesh::Surface;
use super::objects;
use crate::semantic_kitti::class;

/// Rec. 709 luminance weights of linear RGB.
const LUMA: Vec3 = Vec3::new(0.2126, 0.7152, 0.0722);

/// Facade colours of plastered, panelled and painted walls (linear albedo).
const FACADES: [[f32; 3]; 10] = [
    [0.70, 0.69, 0.65], // white plaster
    [0.66, 0.58, 0.42], // cream
    [0.58, 0.42, 0.17], // ochre
    [0.45, 0.20, 0.11], // terracotta
    [0.35, 0.35, 0.33], // grey concrete
    [0.52, 0.52, 0.50], // light grey
    [0.36, 0.42, 0.46], // blue-grey
    [0.42, 0.50, 0.38], // pale green
    [0.64, 0.40, 0.30], // salmon
    [0.14, 0.14, 0.15], // dark grey cladding
];

/// Brick colours (linear albedo).
const BRICKS: [[f32; 3]; 4] = [
    [0.32, 0.11, 0.07], // red
    [0.22, 0.12, 0.08], // brown
    [0.52, 0.42, 0.25], // yellow
    [0.25, 0.08, 0.05], // dark red
];

/// Car paints with their rough share of real fleets (white, black, grey, silver lead).
const CAR_PAINTS: [([f32; 3], f32); 9] = [
    ([0.72, 0.72, 0.70], 0.24),   // white
    ([0.025, 0.025, 0.028], 0.2), // black
    ([0.12, 0.12, 0.13], 0.17),   // grey
    ([0.42, 0.43, 0.45], 0.13),   // silver
    ([0.03, 0.07, 0.24], 0.09),   // blue
    ([0.50, 0.04, 0.03], 0.08),   // red
    ([0.30, 0.22, 0.13], 0.04),   // beige / brown
    ([0.05, 0.16, 0.08], 0.02),   // green
    ([0.75, 0.42, 0.04], 0.03),   // yellow / orange
];

/// Sidewalk paving colours (linear albedo).
const PAVINGS: [[f32; 3]; 5] = [
    [0.34, 0.33, 0.31], // grey concrete
    [0.45, 0.44, 0.41], // light concrete
    [0.40, 0.34, 0.26], // beige
    [0.32, 0.17, 0.12], // red pavers
    [0.17, 0.17, 0.18], // anthracite
];

/// Grass colours (linear albedo).
const GRASSES: [[f32; 3]; 4] = [
    [0.10, 0.22, 0.05], // lush
    [0.16, 0.22, 0.08], // ordinary
    [0.26, 0.24, 0.10], // dry
    [0.07, 0.13, 0.04], // dark
];

/// Foliage colours (linear albedo).
const LEAVES: [[f32; 3]; 5] = [
    [0.06, 0.16, 0.04],
    [0.04, 0.10, 0.03],
    [0.10, 0.18, 0.05],
    [0.08, 0.14, 0.06],
    [0.18, 0.15, 0.04], // early autumn
];

/// Fence colours (linear albedo).
const FENCES: [[f32; 3]; 5] = [
    [0.30, 0.22, 0.14], // wood
    [0.32, 0.31, 0.29], // weathered wood
    [0.05, 0.12, 0.07], // green paint
    [0.65, 0.65, 0.62], // white paint
    [0.04, 0.04, 0.04], // black metal
];

/// Surface pattern of a building wall.
#[derive(Debug, Clone, Copy, PartialEq)]
enum WallStyle {
    /// Render with low-frequency stains and vertical run-off streaks.
    Plaster,
    /// Running-bond brickwork: course height and brick length (mortar included), metres.
    Brick { course_m: f32, brick_m: f32 },
    /// Cladding panels: width and height, metres, with dark joints.
    Panels { width_m: f32, height_m: f32 },
    /// Square glazed tiles of side `size_m` (grout included), each a shade between the facade's
    /// colour and `alt`, with light grout: a mosaic.
    Tiles { size_m: f32, alt: Vec3 },
}

/// One facade look: colour and pattern.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Facade {
    colour: Vec3,
    style: WallStyle,
}

/// Number of facade looks a scene draws (the stock wall materials map onto them by a hash).
const FACADE_LOOKS: usize = 8;

/// A scene's drawn appearance: its lighting, palettes and texture styles.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Appearance {
    /// The drawn sun and sky (exposure from the scene's `lighting`).
    pub(crate) lighting: LightingConfig,
    /// Cloud cover in `[0, 1]` (dims the sun disc of the sky).
    pub(crate) overcast: f32,
    seed: u64,
    contrast: f32,
    brightness_jitter: f32,
    /// Hue jitter as a fraction of a full turn.
    hue_jitter: f32,
    saturation_jitter: f32,
    road: Vec3,
    parking: Vec3,
    marking: Vec3,
    paving: Vec3,
    /// Paving unit along the two plane axes, metres, and whether rows are offset by half a unit.
    paving_unit: [f32; 2],
    paving_running_bond: bool,
    paving_joint_m: f32,
    grass: Vec3,
    soil_cover: f32,
    leaves: Vec3,
    leaves_alt: Vec3,
    fence: Vec3,
    fence_plank_m: f32,
    facades: [Facade; FACADE_LOOKS],
}

fn uniform(rng: &mut ChaCha8Rng, [lo, hi]: [f32; 2]) -> f32 {
    if hi > lo {
        rng.random_range(lo..=hi)
    } else {
        lo
    }
}

fn pick<const N: usize>(rng: &mut ChaCha8Rng, palette: &[[f32; 3]; N]) -> Vec3 {
    Vec3::from(palette[rng.random_range(0..N)])
}

/// Relative linear RGB of black-body light at `kelvin`, white (1, 1, 1) at 6500 K: Planck's law
/// sampled at 610, 550 and 465 nm.
pub(crate) fn blackbody_rgb(kelvin: f32) -> Vec3 {
    let planck = |lambda_um: f64, t: f64| {
        const C2_UM_K: f64 = 14_387.77;
        lambda_um.powi(-5) / ((C2_UM_K / (lambda_um * t)).exp() - 1.0)
    };
    let t = f64::from(kelvin.clamp(1000.0, 40_000.0));
    let ch = |l: f64| (planck(l, t) / planck(l, 6500.0)) as f32;
    Vec3::new(ch(0.610), ch(0.550), ch(0.465))
}

/// The colour with luminance `lum` (black stays black).
fn with_luminance(c: Vec3, lum: f32) -> Vec3 {
    let l = c.dot(LUMA);
    if l > 0.0 { c * (lum / l) } else { Vec3::ZERO }
}

/// Redraws `share` of the facade looks from the whole colour wheel, each look by its own stream
/// of `seed` (so share 0 leaves the stock draw untouched, and a larger share keeps the looks a
/// smaller one redrew): hue uniform, saturation `[0.3, 0.9]` and value `[0.15, 0.7]` of linear
/// albedo; half the redrawn looks are mosaic tiles with a second colour near the first, the rest
/// panels or render.
fn wide_facades(
    mut looks: [Facade; FACADE_LOOKS],
    share: f32,
    seed: u64,
) -> [Facade; FACADE_LOOKS] {
    if share <= 0.0 {
        return looks;
    }
    for (i, look) in looks.iter_mut().enumerate() {
        let mut rng = ChaCha8Rng::seed_from_u64(splitmix(seed ^ 0xFAC_ADE0 ^ i as u64));
        if rng.random::<f32>() >= share {
            continue;
        }
        let hue = rng.random::<f32>();
        let sat = rng.random_range(0.3..=0.9f32);
        let val = rng.random_range(0.15..=0.7f32);
        let colour = hsv_to_rgb([hue, sat, val]);
        let style = match rng.random_range(0..4u32) {
            0 | 1 => {
                let alt = [
                    hue + rng.random_range(-0.04..=0.04f32),
                    (sat * rng.random_range(0.6..=1.1f32)).min(1.0),
                    val * rng.random_range(0.5..=1.3f32),
                ];
                WallStyle::Tiles {
                    size_m: rng.random_range(0.1..=0.4f32),
                    alt: hsv_to_rgb(alt).min(Vec3::ONE),
                }
            }
            2 => WallStyle::Panels {
                width_m: rng.random_range(0.6..1.6f32),
                height_m: rng.random_range(0.4..1.2f32),
            },
            _ => WallStyle::Plaster,
        };
        *look = Facade { colour, style };
    }
    looks
}

impl Appearance {
    /// The appearance of the scene with `scene_seed`: sun, sky, palettes and texture styles drawn
    /// within `cfg`'s ranges; `base` is the clear-sky reference (its sun and ambient luminance, sky
    /// colours and exposure).
    pub(crate) fn draw(cfg: &AppearanceConfig, base: &LightingConfig, scene_seed: u64) -> Self {
        let seed = splitmix(scene_seed ^ 0xA99E_A4A7_CE5E_ED00);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);

        // sun and sky
        let elevation = uniform(&mut rng, cfg.sun_elevation_deg);
        let azimuth = uniform(&mut rng, cfg.sun_azimuth_deg).rem_euclid(360.0);
        // a low sun shines through more air: no bluer than 2000 K + 300 K per degree of elevation
        let kelvin = uniform(&mut rng, cfg.sun_temperature_k).min(2000.0 + 300.0 * elevation);
        let overcast = uniform(&mut rng, cfg.overcast).clamp(0.0, 1.0);
        let haze = rng.random_range(0.0..0.4f32);
        let sun_lum = Vec3::from(base.sun_rgb).dot(LUMA);
        let amb_lum = Vec3::from(base.sky_ambient_rgb).dot(LUMA);
        let hor_lum = Vec3::from(base.sky_horizon_rgb).dot(LUMA);
        let sun = with_luminance(blackbody_rgb(kelvin), sun_lum * (1.0 - 0.85 * overcast));
        // clouds turn the blue sky grey and brighter at the zenith (CIE overcast sky: the zenith about
        // three times the horizon radiance; here a milder 1.3x) and scatter the sun into the ambient
        let ambient =
            Vec3::from(base.sky_ambient_rgb).lerp(Vec3::splat(amb_lum + 0.3 * sun_lum), overcast);
        let horizon = Vec3::from(base.sky_horizon_rgb);
        let zenith = Vec3::from(base.sky_zenith_rgb)
            .lerp(horizon, haze)
            .lerp(Vec3::splat(0.9 * hor_lum), overcast);
        let horizon = horizon.lerp(Vec3::splat(0.7 * hor_lum), overcast);
        let lighting = LightingConfig {
            sun_azimuth_deg: azimuth,
            sun_elevation_deg: elevation,
            sun_rgb: sun.to_array(),
            sky_ambient_rgb: ambient.to_array(),
            sky_zenith_rgb: zenith.to_array(),
            sky_horizon_rgb: horizon.to_array(),
            exposure: base.exposure,
        };

        // class palettes and texture styles
        let grey = uniform(&mut rng, cfg.road_albedo);
        let tint = rng.random_range(-0.04..0.06f32);
        let road = Vec3::new(grey * (1.0 + tint), grey, grey * (1.0 - tint));
        let parking = road * rng.random_range(0.9..1.3f32);
        let marking = Vec3::splat(rng.random_range(0.55..0.8f32)) * Vec3::new(1.0, 1.0, 0.96);
        let paving = pick(&mut rng, &PAVINGS);
        let (paving_unit, paving_running_bond, paving_joint_m) = match rng.random_range(0..3u32) {
            0 => {
                let s = rng.random_range(0.3..0.6f32);
                ([s, s], false, rng.random_range(0.008..0.015f32))
            }
            1 => {
                let l = rng.random_range(0.18..0.26f32);
                ([l, l * 0.5], true, rng.random_range(0.004..0.008f32))
            }
            _ => {
                let s = rng.random_range(0.9..1.5f32);
                ([s, s], false, rng.random_range(0.01..0.02f32))
            }
        };
        let grass = pick(&mut rng, &GRASSES);
        let soil_cover = rng.random_range(0.0..0.6f32);
        let leaves = pick(&mut rng, &LEAVES);
        let leaves_alt = pick(&mut rng, &LEAVES);
        let fence = pick(&mut rng, &FENCES);
        let fence_plank_m = rng.random_range(0.08..0.16f32);
        let facades = std::array::from_fn(|_| {
            let u = rng.random::<f32>();
            if u < 0.3 {
                Facade {
                    colour: pick(&mut rng, &BRICKS),
                    style: WallStyle::Brick {
                        course_m: rng.random_range(0.07..0.09f32),
                        brick_m: rng.random_range(0.21..0.3f32),
                    },
                }
            } else if u < 0.55 {
                Facade {
                    colour: pick(&mut rng, &FACADES),
                    style: WallStyle::Panels {
                        width_m: rng.random_range(0.6..1.6f32),
                        height_m: rng.random_range(0.4..1.2f32),
                    },
                }
            } else {
                Facade {
                    colour: pick(&mut rng, &FACADES),
                    style: WallStyle::Plaster,
                }
            }
        });
        let facades = wide_facades(facades, cfg.wide_facade_share, seed);
        Appearance {
            lighting,
            overcast,
            seed,
            contrast: cfg.texture_contrast,
            brightness_jitter: cfg.brightness_jitter,
            hue_jitter: cfg.hue_jitter_deg / 360.0,
            saturation_jitter: cfg.saturation_jitter,
            road,
            parking,
            marking,
            paving,
            paving_unit,
            paving_running_bond,
            paving_joint_m,
            grass,
            soil_cover,
            leaves,
            leaves_alt,
            fence,
            fence_plank_m,
            facades,
        }
    }

    /// A texture factor `f` (1 = the base colour) at the configured contrast, never negative.
    fn tex(&self, f: f32) -> f32 {
        (1.0 + self.contrast * (f - 1.0)).max(0.0)
    }

    /// Per-surface colour jitter in HSV: hue, saturation and value moved by hashes of `key`.
    fn jitter(&self, c: Vec3, key: u64) -> Vec3 {
        let r = |stream: u64| 2.0 * unit(splitmix(self.seed ^ key ^ stream)) - 1.0;
        let [h, s, v] = rgb_to_hsv(c);
        let h = (h + self.hue_jitter * r(0x11)).rem_euclid(1.0);
        let s = (s * (1.0 + self.saturation_jitter * r(0x22))).clamp(0.0, 1.0);
        let v = v * (1.0 + self.brightness_jitter * r(0x33));
        hsv_to_rgb([h, s, v])
    }

    /// Albedo (linear RGB, each in `[0, 1]`) of `surface` at world point `p` with unit normal `n`,
    /// band-limited to a pixel footprint of `footprint_m` metres.
    pub(crate) fn albedo(&self, surface: &Surface, p: Vec3, n: Vec3, footprint_m: f32) -> Vec3 {
        let m = &surface.material;
        let fp = if footprint_m.is_finite() {
            footprint_m.max(1e-4)
        } else {
            1e3
        };
        let key = material_key(m) ^ u64::from(surface.instance).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let stock_albedo = Vec3::from(m.albedo);
        let c = match m.class {
            class::ROAD => self.asphalt(self.jitter(self.road, key), p, fp, 0x100),
            class::PARKING => self.asphalt(self.jitter(self.parking, key), p, fp, 0x200),
            class::LANE_MARKING => self.paint_marking(self.jitter(self.marking, key), p, fp),
            class::SIDEWALK => self.paving(self.jitter(self.paving, key), p, n, fp),
            class::TERRAIN => self.grass(self.jitter(self.grass, key), p, fp),
            class::VEGETATION => self.foliage(p, fp, key),
            class::TRUNK => self.bark(self.jitter(stock_albedo, key), p, fp),
            class::FENCE => self.planks(self.jitter(self.fence, key), p, n, fp),
            class::POLE => {
                let g = fbm2(self.seed ^ 0x700, p.x + p.y, p.z, 0.6, 3, fp);
                self.jitter(stock_albedo, key) * self.tex(1.0 + 0.12 * g)
            }
            class::BUILDING => self.building(m, p, n, fp, key),
            c if is_vehicle(c) => self.vehicle(m, surface.instance, key),
            _ => self.jitter(stock_albedo, key),
        };
        c.clamp(Vec3::ZERO, Vec3::ONE)
    }

    /// Asphalt: fine aggregate grain, large-scale wear, darker repair patches and occasional cracks.
    fn asphalt(&self, base: Vec3, p: Vec3, fp: f32, stream: u64) -> Vec3 {
        let s = self.seed ^ stream;
        let (x, y) = (p.x, p.y);
        let grain = fbm2(s, x, y, 0.25, 5, fp);
        let mottle = fbm2(s ^ 5, x, y, 2.0, 2, fp);
        let wear = fbm2(s ^ 1, x, y, 14.0, 3, fp);
        let patch = smoothstep(0.66, 0.71, value2(s ^ 2, x / 7.0 + 0.5, y / 7.0 + 0.5));
        let mut f = 1.0 + 0.4 * grain + 0.15 * mottle + 0.25 * wear - 0.3 * patch;
        let crack_mask = smoothstep(0.58, 0.68, value2(s ^ 3, x / 11.0, y / 11.0));
        if crack_mask > 0.0 {
            // a crack follows an iso-line of a noise field; its distance to the line in metres is
            // about |value - 1/2| times the field's wavelength
            let d = (value2(s ^ 4, x / 2.5, y / 2.5) - 0.5).abs() * 2.5;
            f *= 1.0 - 0.55 * crack_mask * line_at(d, 0.012, fp, 2.5);
        }
        base * self.tex(f)
    }

    /// Lane paint: patchy wear and a little grain.
    fn paint_marking(&self, base: Vec3, p: Vec3, fp: f32) -> Vec3 {
        let s = self.seed ^ 0x300;
        let wear = smoothstep(0.5, 0.85, value2(s, p.x / 0.8, p.y / 0.8));
        let grain = fbm2(s ^ 1, p.x, p.y, 0.25, 3, fp);
        base * self.tex(1.0 - 0.4 * wear + 0.12 * grain)
    }

    /// Sidewalk paving: slabs or running-bond pavers with joints and per-unit shade.
    fn paving(&self, base: Vec3, p: Vec3, n: Vec3, fp: f32) -> Vec3 {
        let s = self.seed ^ 0x400;
        let (a, b) = plane_coords(p, n);
        let [pu, pv] = self.paving_unit;
        let row = (b / pv).floor();
        let a = if self.paving_running_bond && (row as i64) & 1 == 1 {
            a + 0.5 * pu
        } else {
            a
        };
        let col = (a / pu).floor();
        let resolve = (pu.min(pv) / fp - 1.0).clamp(0.0, 1.0);
        let unit_shade = 0.18 * (2.0 * lattice(s, col as i64, row as i64, 0) - 1.0) * resolve;
        let grain = fbm2(s ^ 1, a, b, 0.3, 4, fp);
        let joint = line_coverage(a, pu, self.paving_joint_m, fp).max(line_coverage(
            b,
            pv,
            self.paving_joint_m,
            fp,
        ));
        let f = (1.0 + unit_shade) * (1.0 + 0.2 * grain) * (1.0 - 0.55 * joint);
        base * self.tex(f)
    }

    /// Grass with soil patches.
    fn grass(&self, base: Vec3, p: Vec3, fp: f32) -> Vec3 {
        let s = self.seed ^ 0x500;
        let fine = fbm2(s, p.x, p.y, 0.25, 4, fp);
        let mid = fbm2(s ^ 1, p.x, p.y, 2.5, 3, fp);
        let soil = self.soil_cover * smoothstep(0.6, 0.72, value2(s ^ 2, p.x / 5.0, p.y / 5.0));
        let soil_colour = Vec3::new(0.16, 0.11, 0.07);
        let c = base.lerp(soil_colour, soil * self.contrast.min(1.0));
        c * self.tex(1.0 + 0.5 * fine + 0.25 * mid)
    }

    /// Leaves: high-frequency light and shade at leaf scale, darker gaps between clumps and a
    /// slowly varying hue between the scene's two foliage colours.
    fn foliage(&self, p: Vec3, fp: f32, key: u64) -> Vec3 {
        let s = self.seed ^ 0x600;
        let fine = fbm3(s, p, 0.3, 3, fp);
        let clump = fbm3(s ^ 1, p, 1.6, 2, fp);
        let hue = value3(s ^ 2, p / 2.5);
        let base = self
            .jitter(self.leaves, key)
            .lerp(self.jitter(self.leaves_alt, key ^ 1), hue);
        base * self.tex((1.0 + 0.8 * fine + 0.5 * clump).max(0.15))
    }

    /// Bark: vertical furrows.
    fn bark(&self, base: Vec3, p: Vec3, fp: f32) -> Vec3 {
        let s = self.seed ^ 0x800;
        let furrow = 2.0 * value3(s, Vec3::new(p.x / 0.05, p.y / 0.05, p.z / 0.6)) - 1.0;
        base * self.tex(1.0 + 0.35 * furrow * fade(0.05, fp))
    }

    /// Vertical planks with dark gaps and wood grain.
    fn planks(&self, base: Vec3, p: Vec3, n: Vec3, fp: f32) -> Vec3 {
        let s = self.seed ^ 0x900;
        let (a, z) = plane_coords(p, n);
        let w = self.fence_plank_m;
        let plank = (a / w).floor() as i64;
        let shade = 0.15 * (2.0 * lattice(s, plank, 0, 0) - 1.0) * fade(w, fp);
        let grain = (2.0 * value2(s ^ 1, a / 0.02, z / 0.7) - 1.0) * fade(0.02, fp);
        let gap = line_coverage(a, w, 0.01, fp);
        base * self.tex((1.0 + shade + 0.1 * grain) * (1.0 - 0.6 * gap))
    }

    /// Walls (the scene's facade looks), windows (varying sky reflections) and roofs.
    fn building(&self, m: &Material, p: Vec3, n: Vec3, fp: f32, key: u64) -> Vec3 {
        let s = self.seed ^ 0xA00;
        let (u, v) = plane_coords(p, n);
        if m.albedo == objects::WINDOW.albedo {
            let reflect = 0.6 + 2.4 * value2(s, u / 5.0, v / 5.0);
            return self.jitter(Vec3::from(m.albedo), key) * self.tex(reflect);
        }
        if m.albedo == objects::ROOF.albedo {
            let g = fbm2(s ^ 1, u, v, 1.0, 3, fp);
            return self.jitter(Vec3::from(m.albedo), key) * self.tex(1.0 + 0.2 * g);
        }
        let look = self.facades[(splitmix(key ^ self.seed) % FACADE_LOOKS as u64) as usize];
        let base = self.jitter(look.colour, key);
        // a wide, gentle variation along the street so one look differs between buildings
        let broad = fbm2(s ^ 2, u, v, 25.0, 2, fp);
        let vertical = n.z.abs() < 0.7;
        let plinth = if vertical && v < 0.75 { 0.8 } else { 1.0 };
        let f = match look.style {
            WallStyle::Plaster => {
                let stains = fbm2(s ^ 3, u, v, 4.0, 3, fp);
                let fine = fbm2(s ^ 4, u, v, 0.2, 3, fp);
                let streaks = (2.0 * value2(s ^ 5, u / 0.5, v / 5.0) - 1.0) * fade(0.5, fp);
                1.0 + 0.22 * stains + 0.1 * fine + 0.1 * streaks
            }
            WallStyle::Brick { course_m, brick_m } => {
                let row = (v / course_m).floor();
                let a = if (row as i64) & 1 == 1 {
                    u + 0.5 * brick_m
                } else {
                    u
                };
                let col = (a / brick_m).floor();
                let shade = 2.0 * lattice(s ^ 6, col as i64, row as i64, 1) - 1.0;
                let shade = 0.3 * shade * fade(course_m, fp);
                let mortar =
                    line_coverage(a, brick_m, 0.01, fp).max(line_coverage(v, course_m, 0.01, fp));
                // light mortar: the brick colour pulled toward grey
                let brick = 1.0 + shade;
                let mortar_f = 0.45 / base.dot(LUMA).max(0.02);
                brick + (mortar_f - brick) * mortar * 0.8
            }
            WallStyle::Panels { width_m, height_m } => {
                let (col, row) = ((u / width_m).floor(), (v / height_m).floor());
                let shade = 2.0 * lattice(s ^ 7, col as i64, row as i64, 2) - 1.0;
                let joint =
                    line_coverage(u, width_m, 0.015, fp).max(line_coverage(v, height_m, 0.015, fp));
                (1.0 + 0.12 * shade * fade(width_m.min(height_m), fp)) * (1.0 - 0.6 * joint)
            }
            WallStyle::Tiles { size_m, alt } => {
                let (col, row) = ((u / size_m).floor() as i64, (v / size_m).floor() as i64);
                let fd = fade(size_m, fp);
                // each tile a shade between the two colours, fading to their mean beyond the footprint
                let t = 0.5 + (lattice(s ^ 8, col, row, 3) - 0.5) * fd;
                let shade = (2.0 * lattice(s ^ 9, col, row, 4) - 1.0) * fd;
                let tile = base.lerp(self.jitter(alt, key), t) * (1.0 + 0.15 * shade);
                let grout =
                    line_coverage(u, size_m, 0.006, fp).max(line_coverage(v, size_m, 0.006, fp));
                let grout_rgb = Vec3::splat(0.5);
                let f = self.tex((1.0 + 0.15 * broad) * plinth);
                return (tile.lerp(grout_rgb, 0.8 * grout) * f).clamp(Vec3::ZERO, Vec3::ONE);
            }
        };
        base * self.tex(f * (1.0 + 0.15 * broad) * plinth)
    }

    /// Vehicles: the body in a paint of its instance (real-fleet colour shares), glass and tyres
    /// in their stock colours, everything jittered per instance.
    fn vehicle(&self, m: &Material, instance: u16, key: u64) -> Vec3 {
        let stock_albedo = Vec3::from(m.albedo);
        if m.albedo == stock::GLASS.albedo || m.albedo == stock::TYRE.albedo {
            return self.jitter(stock_albedo, key);
        }
        let u = unit(splitmix(
            self.seed ^ 0xB00 ^ u64::from(instance).wrapping_mul(0xD6E8_FEB8_6659_FD93),
        ));
        let total: f32 = CAR_PAINTS.iter().map(|(_, w)| w).sum();
        let mut acc = 0.0;
        let mut paint = Vec3::from(CAR_PAINTS[0].0);
        for (c, w) in CAR_PAINTS {
            acc += w / total;
            paint = Vec3::from(c);
            if u < acc {
                break;
            }
        }
        // a truck's cargo box or a trailer's shell keeps its light stock colour
        if stock_albedo.dot(LUMA) > 0.6 && !matches!(m.class, class::CAR | class::MOVING_CAR) {
            paint = stock_albedo;
        }
        self.jitter(paint, key)
    }
}

/// True for the vehicle classes (parked and moving).
fn is_vehicle(c: u16) -> bool {
    matches!(
        c,
        class::CAR
            | class::BUS
            | class::TRUCK
            | class::OTHER_VEHICLE
            | class::MOVING_CAR
            | class::MOVING_BUS
            | class::MOVING_TRUCK
            | class::MOVING_OTHER_VEHICLE
    )
}

/// A hash of a material's albedo and class (which stock material or palette entry it is).
fn material_key(m: &Material) -> u64 {
    let [r, g, b] = m.albedo.map(f32::to_bits);
    splitmix(
        u64::from(r) ^ (u64::from(g) << 32) ^ splitmix(u64::from(b) ^ (u64::from(m.class) << 32)),
    )
}

/// The two coordinates of the plane a surface mostly lies in: `(x, y)` for ground, `(y, z)` or
/// `(x, z)` for walls facing x or y.
fn plane_coords(p: Vec3, n: Vec3) -> (f32, f32) {
    let a = n.abs();
    if a.z >= a.x && a.z >= a.y {
        (p.x, p.y)
    } else if a.x >= a.y {
        (p.y, p.z)
    } else {
        (p.x, p.z)
    }
}

/// The top 24 bits of a hash as a number in `[0, 1)`.
#[inline]
fn unit(h: u64) -> f32 {
    (h >> 40) as f32 / (1u64 << 24) as f32
}

/// A uniform number in `[0, 1)` at an integer lattice point.
#[inline]
fn lattice(seed: u64, x: i64, y: i64, z: i64) -> f32 {
    unit(splitmix(
        seed ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            ^ (z as u64).wrapping_mul(0x1656_67B1_9E37_79F9),
    ))
}

#[inline]
fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    smooth(((x - e0) / (e1 - e0)).clamp(0.0, 1.0))
}

fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a + (b - a) * t
}

/// 2-D value noise in `[0, 1]`: lattice values blended with a smoothstep (unit wavelength).
fn value2(seed: u64, x: f32, y: f32) -> f32 {
    let (fx, fy) = (x.floor(), y.floor());
    let (tx, ty) = (smooth(x - fx), smooth(y - fy));
    let (ix, iy) = (fx as i64, fy as i64);
    let l = |dx: i64, dy: i64| lattice(seed, ix + dx, iy + dy, 0);
    lerp(lerp(l(0, 0), l(1, 0), tx), lerp(l(0, 1), l(1, 1), tx), ty)
}

/// 3-D value noise in `[0, 1]` (unit wavelength).
fn value3(seed: u64, p: Vec3) -> f32 {
    let f = p.floor();
    let t = (p - f).to_array().map(smooth);
    let (ix, iy, iz) = (f.x as i64, f.y as i64, f.z as i64);
    let l = |dx: i64, dy: i64, dz: i64| lattice(seed, ix + dx, iy + dy, iz + dz);
    let plane = |dz: i64| {
        lerp(
            lerp(l(0, 0, dz), l(1, 0, dz), t[0]),
            lerp(l(0, 1, dz), l(1, 1, dz), t[0]),
            t[1],
        )
    };
    lerp(plane(0), plane(1), t[2])
}

/// Weight of a feature of size `wavelength_m` seen with a pixel footprint `fp`: 1 when it spans at
/// least two footprints, 0 at one footprint or less.
#[inline]
fn fade(wavelength_m: f32, fp: f32) -> f32 {
    (wavelength_m / fp - 1.0).clamp(0.0, 1.0)
}

/// Fractal value noise in `[-1, 1]` (mean 0): `octaves` octaves from `wavelength_m` down, halving
/// wavelength and amplitude each time; octaves finer than the footprint fade to their mean.
fn fbm2(seed: u64, x: f32, y: f32, wavelength_m: f32, octaves: u32, fp: f32) -> f32 {
    let (mut sum, mut norm, mut amp, mut lam) = (0.0, 0.0, 1.0, wavelength_m);
    for k in 0..octaves {
        let w = fade(lam, fp);
        if w > 0.0 {
            let o = 0.37 * k as f32; // decorrelate the octaves' lattices
            let v = value2(seed ^ (u64::from(k + 1) << 48), x / lam + o, y / lam - o);
            sum += amp * w * (2.0 * v - 1.0);
        }
        norm += amp;
        amp *= 0.5;
        lam *= 0.5;
    }
    sum / norm
}

/// 3-D fractal value noise in `[-1, 1]`, as [`fbm2`].
fn fbm3(seed: u64, p: Vec3, wavelength_m: f32, octaves: u32, fp: f32) -> f32 {
    let (mut sum, mut norm, mut amp, mut lam) = (0.0, 0.0, 1.0, wavelength_m);
    for k in 0..octaves {
        let w = fade(lam, fp);
        if w > 0.0 {
            let v = value3(
                seed ^ (u64::from(k + 1) << 48),
                p / lam + Vec3::splat(0.37 * k as f32),
            );
            sum += amp * w * (2.0 * v - 1.0);
        }
        norm += amp;
        amp *= 0.5;
        lam *= 0.5;
    }
    sum / norm
}

/// Coverage in `[0, 1]` of a line of `width_m` at distance `d` (metres), box-filtered over a
/// footprint `fp`: a line thinner than the footprint spreads into `width / footprint`, and once the
/// lines (`period_m` apart) are closer than two footprints, into their mean coverage.
fn line_at(d: f32, width_m: f32, fp: f32, period_m: f32) -> f32 {
    let mean = (width_m / period_m).min(1.0);
    let half = 0.5 * width_m.max(fp);
    let sharp = 1.0 - smoothstep(half - 0.5 * fp, half + 0.5 * fp, d);
    let line = sharp * (width_m / width_m.max(fp));
    let t = (2.0 * fp / period_m).clamp(0.0, 1.0);
    lerp(line, mean, t * t)
}

/// Coverage of grid lines `period_m` apart (at multiples of the period) at coordinate `x`.
fn line_coverage(x: f32, period_m: f32, width_m: f32, fp: f32) -> f32 {
    let r = (x / period_m).rem_euclid(1.0);
    let d = r.min(1.0 - r) * period_m;
    line_at(d, width_m, fp, period_m)
}

/// Linear RGB to HSV (`h` in `[0, 1)` turns).
fn rgb_to_hsv(c: Vec3) -> [f32; 3] {
    let (r, g, b) = (c.x, c.y, c.z);
    let max = r.max(g).max(b);
    let min = r.min(g).min(b);
    let d = max - min;
    let h = if d <= 0.0 {
        0.0
    } else if max == r {
        ((g - b) / d).rem_euclid(6.0) / 6.0
    } else if max == g {
        ((b - r) / d + 2.0) / 6.0
    } else {
        ((r - g) / d + 4.0) / 6.0
    };
    let s = if max > 0.0 { d / max } else { 0.0 };
    [h, s, max]
}

/// HSV (`h` in turns) to linear RGB.
fn hsv_to_rgb([h, s, v]: [f32; 3]) -> Vec3 {
    let h6 = h.rem_euclid(1.0) * 6.0;
    let i = h6.floor();
    let f = h6 - i;
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f)));
    match i as i32 {
        0 => Vec3::new(v, t, p),
        1 => Vec3::new(q, v, p),
        2 => Vec3::new(p, v, t),
        3 => Vec3::new(p, q, v),
        4 => Vec3::new(t, p, v),
        _ => Vec3::new(v, p, q),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::material::stock;

    fn extreme() -> AppearanceConfig {
        AppearanceConfig {
            randomize: true,
            sun_temperature_k: [2000.0, 12000.0],
            road_albedo: [0.0, 1.0],
            brightness_jitter: 1.0,
            hue_jitter_deg: 180.0,
            saturation_jitter: 1.0,
            texture_contrast: 2.0,
            ..AppearanceConfig::default()
        }
    }

    /// Every material the generator uses, plus odd ones (white, black, saturated).
    fn materials() -> Vec<Material> {
        let mut v = vec![
            stock::ROAD,
            stock::PARKING,
            stock::LANE_MARKING,
            stock::SIDEWALK,
            stock::TERRAIN,
            stock::VEGETATION,
            stock::TRUNK,
            stock::POLE,
            stock::SIGN,
            stock::FENCE,
            stock::TYRE,
            stock::GLASS,
            stock::CLOTH,
            stock::SKIN,
            objects::WINDOW,
            objects::ROOF,
        ];
        for cls in [
            class::BUILDING,
            class::CAR,
            class::MOVING_CAR,
            class::TRUCK,
            class::OTHER_VEHICLE,
            class::PERSON,
            class::ROAD,
        ] {
            for albedo in [
                [1.0, 1.0, 1.0],
                [0.0, 0.0, 0.0],
                [0.9, 0.05, 0.0],
                [0.7, 0.7, 0.68],
            ] {
                v.push(Material::new(albedo, 0.5, cls));
            }
        }
        v
    }

    #[test]
    fn albedo_stays_in_the_unit_cube_everywhere() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mats = materials();
        let base = LightingConfig::default();
        let wide = AppearanceConfig {
            wide_facade_share: 1.0,
            ..extreme()
        };
        for (i, cfg) in [AppearanceConfig::default(), extreme(), wide]
            .iter()
            .enumerate()
        {
            for seed in 0..8u64 {
                let a = Appearance::draw(cfg, &base, seed);
                for _ in 0..4000 {
                    let m = mats[rng.random_range(0..mats.len())];
                    let surface = Surface {
                        material: m,
                        instance: rng.random_range(0..50u16),
                    };
                    let p = Vec3::new(
                        rng.random_range(-300.0..300.0),
                        rng.random_range(-300.0..300.0),
                        rng.random_range(-2.0..40.0),
                    );
                    let n = Vec3::new(
                        rng.random_range(-1.0..1.0f32),
                        rng.random_range(-1.0..1.0f32),
                        rng.random_range(-1.0..1.0f32),
                    )
                    .try_normalize()
                    .unwrap_or(Vec3::Z);
                    let fp = 10f32.powf(rng.random_range(-4.0..1.0f32));
                    let c = a.albedo(&surface, p, n, fp);
                    assert!(
                        c.is_finite() && c.min_element() >= 0.0 && c.max_element() <= 1.0,
                        "config {i} seed {seed}: {m:?} at {p} -> {c}"
                    );
                }
                // degenerate footprints are harmless
                let s = Surface {
                    material: stock::ROAD,
                    instance: 0,
                };
                for fp in [0.0, -1.0, f32::NAN, f32::INFINITY] {
                    let c = a.albedo(&s, Vec3::new(1.0, 2.0, 0.0), Vec3::Z, fp);
                    assert!(c.is_finite() && c.max_element() <= 1.0, "{fp}: {c}");
                }
            }
        }
    }

    #[test]
    fn road_albedo_spans_the_configured_range_and_varies_within_a_scene() {
        let cfg = AppearanceConfig {
            randomize: true,
            ..AppearanceConfig::default()
        };
        let road = Surface {
            material: stock::ROAD,
            instance: 0,
        };
        let mut means = Vec::new();
        for seed in 0..24u64 {
            let a = Appearance::draw(&cfg, &LightingConfig::default(), seed);
            let vals: Vec<f32> = (0..2000)
                .map(|k| {
                    let p = Vec3::new(k as f32 * 0.137 - 130.0, (k % 37) as f32 * 0.29, 0.0);
                    a.albedo(&road, p, Vec3::Z, 0.005).dot(LUMA)
                })
                .collect();
            let mean = vals.iter().sum::<f32>() / vals.len() as f32;
            let sd =
                (vals.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / vals.len() as f32).sqrt();
            assert!(
                sd > 0.08 * mean,
                "seed {seed}: texture too flat ({sd} vs {mean})"
            );
            means.push(mean);
        }
        let lo = means.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = means.iter().copied().fold(0.0, f32::max);
        assert!(lo < 0.08 && hi > 0.14, "road means {lo}..{hi}");
        // with texture contrast 0 a road is one flat colour again
        let flat = Appearance::draw(
            &AppearanceConfig {
                texture_contrast: 0.0,
                ..cfg
            },
            &LightingConfig::default(),
            1,
        );
        let c0 = flat.albedo(&road, Vec3::new(3.0, 1.0, 0.0), Vec3::Z, 0.01);
        let c1 = flat.albedo(&road, Vec3::new(-40.0, 7.5, 0.0), Vec3::Z, 0.01);
        assert_eq!(c0, c1);
    }

    #[test]
    fn textures_fade_to_their_mean_beyond_the_footprint() {
        // far away (1 m footprint) the asphalt grain is gone: neighbouring points agree
        let a = Appearance::draw(&extreme(), &LightingConfig::default(), 2);
        let road = Surface {
            material: stock::ROAD,
            instance: 0,
        };
        let near = |fp: f32| {
            let c0 = a.albedo(&road, Vec3::new(5.0, 1.0, 0.0), Vec3::Z, fp);
            let c1 = a.albedo(&road, Vec3::new(5.03, 1.02, 0.0), Vec3::Z, fp);
            (c0 - c1).abs().max_element()
        };
        assert!(
            near(2e-3) > 2.0 * near(1.0),
            "{} vs {}",
            near(2e-3),
            near(1.0)
        );
        // grid lines: sharp coverage up close, their mean coverage far away
        assert!(line_coverage(0.0, 0.5, 0.01, 1e-4) > 0.999);
        assert!(line_coverage(0.25, 0.5, 0.01, 1e-4) < 1e-6);
        let mean = (0..1000)
            .map(|k| line_coverage(k as f32 * 0.000_5, 0.5, 0.01, 0.004))
            .sum::<f32>()
            / 1000.0;
        assert!((mean - 0.02).abs() < 0.004, "{mean}");
        assert!((line_coverage(0.13, 0.5, 0.01, 5.0) - 0.02).abs() < 1e-6);
    }

    #[test]
    fn wide_facades_redraw_their_share_of_looks_and_nothing_else() {
        let base = LightingConfig::default();
        let at = |share: f32, seed: u64| {
            let cfg = AppearanceConfig {
                randomize: true,
                wide_facade_share: share,
                ..AppearanceConfig::default()
            };
            Appearance::draw(&cfg, &base, seed)
        };
        let (mut redrawn, mut total, mut saturated, mut tiled) = (0, 0, 0, 0);
        for seed in 0..40u64 {
            let stock = at(0.0, seed);
            let (half, all) = (at(0.5, seed), at(1.0, seed));
            // everything but the facades is the stock draw, byte for byte
            for a in [&half, &all] {
                let mut same = a.clone();
                same.facades = stock.facades;
                assert_eq!(same, stock, "seed {seed}");
            }
            for i in 0..FACADE_LOOKS {
                total += 1;
                let (s, h, w) = (stock.facades[i], half.facades[i], all.facades[i]);
                assert_ne!(w, s, "seed {seed} look {i}: share 1 keeps a stock look");
                // a look the smaller share redrew is the same look at the larger one
                if h != s {
                    redrawn += 1;
                    assert_eq!(h, w, "seed {seed} look {i}");
                }
                if rgb_to_hsv(w.colour)[1] > 0.6 {
                    saturated += 1;
                }
                if let WallStyle::Tiles { size_m, alt } = w.style {
                    tiled += 1;
                    assert!((0.1..=0.4).contains(&size_m), "{size_m}");
                    assert!(
                        alt.min_element() >= 0.0 && alt.max_element() <= 1.0,
                        "{alt}"
                    );
                }
            }
        }
        let frac = |k: i32| k as f64 / total as f64;
        // 320 looks: a binomial share of 0.5 lies within 0.5 +- 0.1 by over 3.5 sigma
        assert!((frac(redrawn) - 0.5).abs() < 0.1, "{}", frac(redrawn));
        assert!((frac(tiled) - 0.5).abs() < 0.1, "{}", frac(tiled));
        // saturation uniform in [0.3, 0.9]: half above 0.6; the stock palettes have none
        assert!((frac(saturated) - 0.5).abs() < 0.1, "{}", frac(saturated));
        assert!(
            FACADES
                .iter()
                .chain(BRICKS.iter())
                .all(|&c| rgb_to_hsv(Vec3::from(c))[1] < 0.85)
        );
    }

    #[test]
    fn mosaic_tiles_vary_between_tiles_and_fade_to_their_mean_beyond_the_footprint() {
        let mut a = Appearance::draw(
            &AppearanceConfig {
                randomize: true,
                ..AppearanceConfig::default()
            },
            &LightingConfig::default(),
            7,
        );
        let (blue, teal) = (Vec3::new(0.05, 0.3, 0.6), Vec3::new(0.05, 0.45, 0.5));
        a.facades = [Facade {
            colour: blue,
            style: WallStyle::Tiles {
                size_m: 0.2,
                alt: teal,
            },
        }; FACADE_LOOKS];
        let wall = Surface {
            material: Material::new([0.5, 0.5, 0.5], 0.5, class::BUILDING),
            instance: 3,
        };
        // a wall facing -y: plane coordinates (x, z); tile centres at odd multiples of 0.1 m,
        // above the plinth
        let at = |x: f32, z: f32, fp: f32| a.albedo(&wall, Vec3::new(x, 5.0, z), -Vec3::Y, fp);
        let centres: Vec<Vec3> = (0..40)
            .map(|k| at(0.1 + 0.2 * k as f32, 3.1, 1e-3))
            .collect();
        // inside one tile the colour is one shade (up to the broad 25 m variation)
        let inside = at(0.13, 3.07, 1e-3);
        assert!(
            (inside - centres[0]).abs().max_element() < 0.01,
            "{inside} {}",
            centres[0]
        );
        let spread = centres
            .iter()
            .map(|c| (*c - centres[0]).abs().max_element())
            .fold(0.0f32, f32::max);
        assert!(spread > 0.05, "tiles all alike: {spread}");
        // every tile is bluish: blue the largest channel, red the smallest
        for c in &centres {
            assert!(c.z > c.x && c.y > c.x, "{c}");
        }
        // seen from far (a footprint of several tiles) the wall is one even colour
        let far: Vec<Vec3> = (0..10)
            .map(|k| at(0.1 + 0.2 * k as f32, 3.1, 2.0))
            .collect();
        let far_spread = far
            .iter()
            .map(|c| (*c - far[0]).abs().max_element())
            .fold(0.0f32, f32::max);
        assert!(far_spread < 0.02, "{far_spread}");
    }

    #[test]
    fn noise_is_bounded_and_deterministic() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for _ in 0..20_000 {
            let p = Vec3::new(
                rng.random_range(-1e3..1e3),
                rng.random_range(-1e3..1e3),
                rng.random_range(-1e3..1e3),
            );
            let v2 = value2(5, p.x, p.y);
            let v3 = value3(5, p);
            let f2 = fbm2(5, p.x, p.y, 0.7, 5, 1e-3);
            let f3 = fbm3(5, p, 0.7, 4, 1e-3);
            assert!((0.0..=1.0).contains(&v2) && (0.0..=1.0).contains(&v3));
            assert!((-1.0..=1.0).contains(&f2) && (-1.0..=1.0).contains(&f3));
            assert_eq!(v3.to_bits(), value3(5, p).to_bits());
        }
        assert_ne!(value2(1, 0.5, 0.5), value2(2, 0.5, 0.5));
    }

    #[test]
    fn colour_helpers_are_consistent() {
        let w = blackbody_rgb(6500.0);
        assert!((w - Vec3::ONE).abs().max_element() < 1e-5, "{w}");
        let warm = blackbody_rgb(3000.0);
        assert!(warm.x > warm.y && warm.y > warm.z, "{warm}");
        let cool = blackbody_rgb(10_000.0);
        assert!(cool.z > cool.y && cool.y > cool.x, "{cool}");
        for c in [
            Vec3::new(0.2, 0.5, 0.1),
            Vec3::new(0.9, 0.1, 0.4),
            Vec3::new(0.3, 0.3, 0.3),
            Vec3::ZERO,
            Vec3::new(0.05, 0.1, 0.7),
        ] {
            let back = hsv_to_rgb(rgb_to_hsv(c));
            assert!((back - c).abs().max_element() < 1e-5, "{c} -> {back}");
        }
    }

    #[test]
    fn sky_draw_follows_the_cloud_cover() {
        let base = LightingConfig::default();
        let clear = Appearance::draw(
            &AppearanceConfig {
                overcast: [0.0, 0.0],
                ..AppearanceConfig::default()
            },
            &base,
            4,
        );
        let grey = Appearance::draw(
            &AppearanceConfig {
                overcast: [1.0, 1.0],
                ..AppearanceConfig::default()
            },
            &base,
            4,
        );
        let (cl, gr) = (&clear.lighting, &grey.lighting);
        // the same seed draws the same sun position; clouds dim it and whiten the sky
        assert_eq!(cl.sun_azimuth_deg, gr.sun_azimuth_deg);
        let lum = |c: [f32; 3]| Vec3::from(c).dot(LUMA);
        assert!(lum(gr.sun_rgb) < 0.2 * lum(cl.sun_rgb));
        assert!(lum(gr.sky_ambient_rgb) > lum(cl.sky_ambient_rgb));
        let blue = |c: [f32; 3]| c[2] - c[0];
        assert!(blue(cl.sky_zenith_rgb) > 0.2 && blue(gr.sky_zenith_rgb).abs() < 1e-4);
        assert_eq!(cl.exposure, base.exposure);
    }
}
