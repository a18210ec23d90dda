//! Quality presets for `voxrad solve --quality draft|default|high`: resolution, direction count,
//! tolerance and tail extrapolation chosen together from the accuracy/time study (`study`), so
//! that no knob is paid for beyond what the others allow. The study on the Cornell box shows the
//! error dominated by direction aliasing, then resolution, with truncated iterations far below
//! both once the tolerance is 1e-3 or less; extrapolation costs nothing and never hurts, so every
//! preset uses it. The direction aliasing is the lamp's direct light: where the emitters are small
//! the direct-light pass (`solve::direct`) gathers it along 5,000 (`draft`), 16,000 (`default`)
//! or 20,000 (`high`) dense directions from the emitters' lines only, which lets the bounces use
//! fewer directions (301 instead of 589 for `default`, 433 instead of 1201 for `high`) at a lower
//! error. On the realistic scenes (an office, a corridor, a furnished room: `tests/data/reference`)
//! the resolution matters most, as their partitions, lamps and furniture are a fraction of a
//! voxel at 32: since the links kept between iterations and the direct pass's bundled walks made
//! solves several times faster, `default` runs at 64 (2026-12-02); since the searches from
//! sides inside solids were left out, it affords 301 bounce directions (2026-12-04: the office
//! went from 1.57 to 1.28 % mean error, read by gathering, in about the same time), with the
//! dense directions capped at 16,000 (the office 1.28 % in 2.6 s, against 1.26 % in 3.3 s at
//! 20,000; its error moves by a few tenths of a percent from one dense count to the next, the
//! lamps' aliasing, measured in `docs/study.md`). `high` runs at 256
//! (2026-12-03): read by gathering (`voxrad probe --gather`), it is within 0.5 % mean and 3 %
//! largest error of the path-traced reference on all four reference scenes, where 128 left the
//! office and the corridor at 0.9 %; 433 directions instead of 589 cost the office 0.06 % of
//! mean error and save a quarter of the time, and a tolerance of 1e-4 instead of 1e-5 changed
//! no scene's error by more than 0.004 % and saves 4 to 5 iterations. Measured error and time of
//! each preset: `docs/study.md`, "Quality presets". Every preset iterates by Chebyshev
//! semi-iteration where the tail extrapolation finds no geometric tail (2026-12-04): on the four
//! reference scenes it took `default` from 50 to 45 iterations in all and `high` from 49 to 44,
//! at the same gathered error within 0.03 % (`docs/study.md`, "Chebyshev in the presets").
//!
//! Options given explicitly on the command line override the preset's.

/// A quality preset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Quality {
    Draft,
    Default,
    High,
}

/// What a preset sets.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Preset {
    pub resolution: u32,
    pub directions: usize,
    pub tolerance: f64,
    pub accelerate: bool,
    /// Chebyshev semi-iteration where the tail extrapolation finds no geometric tail
    /// (`solve::accelerate::Chebyshev`).
    pub chebyshev: bool,
    /// Dense line directions of the direct-light pass where the scene's emitters are small
    /// (`solve::direct`); 0: none.
    pub direct: usize,
}

impl Quality {
    pub const ALL: [Quality; 3] = [Quality::Draft, Quality::Default, Quality::High];

    pub fn name(self) -> &'static str {
        match self {
            Quality::Draft => "draft",
            Quality::Default => "default",
            Quality::High => "high",
        }
    }

    pub fn preset(self) -> Preset {
        match self {
            Quality::Draft => Preset {
                resolution: 32,
                directions: 109,
                tolerance: 1e-2,
                accelerate: true,
                chebyshev: true,
                direct: 5_000,
            },
            Quality::Default => Preset {
                resolution: 64,
                directions: 301,
                tolerance: 1e-4,
                accelerate: true,
                chebyshev: true,
                direct: 16_000,
            },
            Quality::High => Preset {
                resolution: 256,
                directions: 433,
                tolerance: 1e-4,
                accelerate: true,
                chebyshev: true,
                direct: 20_000,
            },
        }
    }
}
