//! What makes real sensors hard, one cause at a time. A profile is a set of effects
//! (`Profile::effects`); `posefuse simulate --effects` adds single ones to a profile, so each cause
//! can be measured alone (docs/DATA.md, "Realism against Waymo's anchors").

use super::street::Profile;

/// One modelled cause of difficulty. Output without an effect is byte-identical to output from a
/// simulator that never had it: an effect draws random numbers only when it is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum Effect {
    /// Loose clothing, things in hand and shoulder bags (`street.rs`).
    Dress,
    /// A return whose beam straddles an edge gets a range between the two surfaces (`lidar.rs`).
    MixedPixels,
    /// The beam is a cone, not a ray: a return comes from the nearest surface its footprint
    /// touches, so thin limbs look thicker and their edges smear (`lidar.rs`).
    Footprint,
    /// Dark surfaces return too little light at range and grazing angles (`lidar.rs`).
    Reflectivity,
    /// Arms against the torso: hands in pockets, arms crossed, hands behind the back, arms held
    /// close while walking (`poses.rs`).
    ArmsIn,
    /// The 3D keypoint labels carry a human labeller's error (`dataset.rs`); 2D labels already do.
    LabelNoise,
    /// Forearms that taper to the wrist and flat hands: a wrist catches as few returns as a real
    /// one (`hands.rs`).
    SlimHands,
}

/// The set of effects a simulation runs with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Realism {
    bits: u8,
}

impl Realism {
    pub fn with(mut self, e: Effect) -> Realism {
        self.bits |= 1 << e as u8;
        self
    }

    pub fn has(&self, e: Effect) -> bool {
        self.bits & (1 << e as u8) != 0
    }

    /// The profile's effects plus `extra`.
    pub fn of(profile: Profile, extra: &[Effect]) -> Realism {
        profile.effects().iter().chain(extra).fold(Realism::default(), |r, &e| r.with(e))
    }

    /// The effects that are on, in declaration order (as `dataset.json` records them).
    pub fn effects(&self) -> Vec<Effect> {
        ALL.iter().copied().filter(|&e| self.has(e)).collect()
    }
}

const ALL: [Effect; 7] = [
    Effect::Dress,
    Effect::MixedPixels,
    Effect::Footprint,
    Effect::Reflectivity,
    Effect::ArmsIn,
    Effect::LabelNoise,
    Effect::SlimHands,
];

impl From<Profile> for Realism {
    fn from(p: Profile) -> Realism {
        Realism::of(p, &[])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_profile_is_its_effects_and_extras_add_to_them() {
        assert!(Realism::from(Profile::Clean).effects().is_empty());
        assert_eq!(Profile::default(), Profile::StreetHard, "the library's default is the CLI's");
        assert_eq!(Realism::from(Profile::Street).effects(), [Effect::Dress, Effect::MixedPixels]);
        let r = Realism::of(Profile::Street, &[Effect::LabelNoise, Effect::Footprint, Effect::Footprint]);
        assert_eq!(r.effects(), [Effect::Dress, Effect::MixedPixels, Effect::Footprint, Effect::LabelNoise]);
        assert!(r.has(Effect::Footprint) && !r.has(Effect::ArmsIn));
        assert_eq!(ALL.len(), Effect::SlimHands as usize + 1);
        assert!(ALL.len() <= 8, "effects are bits of a u8");
        let all = ALL.iter().fold(Realism::default(), |r, &e| r.with(e));
        assert_eq!(all.effects(), ALL);
        let hard = Realism::from(Profile::StreetHard);
        // dataset.json spells the profile as the command line does.
        assert_eq!(serde_json::to_string(&Profile::StreetHard).ok().as_deref(), Some("\"street-hard\""));
        assert_eq!(hard, Realism::of(Profile::Street, &[Effect::ArmsIn, Effect::Reflectivity, Effect::LabelNoise]));
    }
}
