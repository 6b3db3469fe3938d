//! The built-in model configs (presets) every command starts from: the core's NeRF-synthetic
//! default, the method's config for spacecraft, and the budget profiles (`budgets/*.toml`,
//! built into the binary). A config file then changes some of a preset's fields
//! ([`crate::train::read_config`]).

use crate::ablation::{APPEARANCE_POSE, EMBEDDING_DIM};
use crate::error::{HostError, Result};
use crate::formats::Format;
use orbit_nerf_core::Config;
use std::path::Path;

/// A built-in config.
#[derive(Clone, Copy, Debug)]
pub struct Preset {
    /// The name commands select it by (`--preset`, a sweep description's `preset`).
    pub name: &'static str,
    /// What it is, for help texts.
    pub about: &'static str,
    source: Source,
}

#[derive(Clone, Copy, Debug)]
enum Source {
    /// A config the crates define.
    Builtin(Config),
    /// A budget file's text (every field, in a `[config]` table).
    Budget(&'static str),
}

/// The preset of the data the NeRF tools use (NeRF-synthetic, nerfstudio).
pub const DEFAULT: &str = "default";
/// The preset of spacecraft data (SPEED+, SHIRT, the simulator's output).
pub const SPACECRAFT: &str = "spacecraft";

/// Every preset, by name.
pub const PRESETS: [Preset; 5] = [
    Preset {
        name: DEFAULT,
        about: "the NeRF-synthetic default: no appearance embeddings, no pose correction, rays drawn uniformly",
        source: Source::Builtin(Config::DEFAULT),
    },
    Preset {
        name: SPACECRAFT,
        about: "the method for a spacecraft on black sky: appearance embeddings and pose correction, 3/4 of the rays on the target, a wider colour MLP",
        source: Source::Builtin(Config {
            embedding_dim: EMBEDDING_DIM,
            pose_correction: APPEARANCE_POSE.pose_correction,
            ..Config::SPACECRAFT
        }),
    },
    Preset {
        name: "tiny",
        about: "the microcontroller-sized budget profile (budgets/tiny.toml)",
        source: Source::Budget(include_str!("../../budgets/tiny.toml")),
    },
    Preset {
        name: "standard",
        about: "the standard budget profile (budgets/standard.toml)",
        source: Source::Budget(include_str!("../../budgets/standard.toml")),
    },
    Preset {
        name: "render",
        about: "the render-only budget profile (budgets/render.toml)",
        source: Source::Budget(include_str!("../../budgets/render.toml")),
    },
];

impl Preset {
    /// The preset's config.
    pub fn config(&self) -> Result<Config> {
        match self.source {
            Source::Builtin(config) => Ok(config),
            Source::Budget(text) => {
                let builtin = Path::new("<built-in>").join(format!("{}.toml", self.name));
                crate::train::parse_config(&builtin, text, &Config::DEFAULT)
            }
        }
    }
}

/// The preset called `name`, or `None` if there is none.
pub fn find(name: &str) -> Option<&'static Preset> {
    PRESETS.iter().find(|p| p.name == name)
}

/// The presets' names, in order.
pub fn names() -> impl Iterator<Item = &'static str> {
    PRESETS.iter().map(|p| p.name)
}

/// The config of the preset `name`; an unknown name is an error naming `origin` and `field`
/// and listing the presets.
pub fn config_of(origin: &Path, field: &str, name: &str) -> Result<Config> {
    match find(name) {
        Some(preset) => preset.config(),
        None => Err(HostError::field(
            origin,
            field,
            format!(
                "`{name}` is no preset ({})",
                names().collect::<Vec<_>>().join(", ")
            ),
        )),
    }
}

/// The preset for data of `format`: the method's for spacecraft folders, the NeRF default for
/// the NeRF tools' formats.
pub fn for_format(format: Format) -> &'static str {
    match format {
        Format::SpeedPlus => SPACECRAFT,
        Format::NerfSynthetic | Format::Nerfstudio => DEFAULT,
    }
}

/// A model's shape in one line: its plane scales and resolutions, the two MLPs' widths, the
/// view-direction degree, the occupancy grid and the rays per step.
pub fn describe(config: &Config) -> String {
    format!(
        "{} scales {:?} x {} features, density MLP {}->{}->{}, colour MLP {}->{}->{}->3, SH degree {}, occupancy {}^3, {} rays/step",
        config.scales,
        &config.resolutions[..config.scales as usize],
        config.features,
        config.density_inputs(),
        config.density_hidden,
        config.density_outputs(),
        config.colour_inputs(),
        config.colour_hidden,
        config.colour_hidden,
        config.sh_bands,
        config.occupancy_res,
        config.rays_per_batch
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_preset_has_a_valid_config() {
        for preset in &PRESETS {
            let config = preset.config().unwrap();
            config.validate().unwrap();
        }
        assert_eq!(find(DEFAULT).unwrap().config().unwrap(), Config::DEFAULT);
        let spacecraft = find(SPACECRAFT).unwrap().config().unwrap();
        assert!(spacecraft.embedding_dim > 0 && spacecraft.pose_correction);
        assert_eq!(
            Config {
                embedding_dim: 0,
                pose_correction: false,
                ..spacecraft
            },
            Config::SPACECRAFT
        );
        assert_eq!(find("tiny").unwrap().config().unwrap().features, 8);
    }

    #[test]
    fn an_unknown_preset_is_an_error_listing_the_names() {
        let error = config_of(Path::new("sweep.toml"), "config", "huge")
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("sweep.toml")
                && error.contains("`config`")
                && error.contains("default, spacecraft, tiny, standard, render"),
            "{error}"
        );
    }
}
