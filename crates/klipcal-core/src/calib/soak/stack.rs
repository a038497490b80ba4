//! PURE: the bed stacks a user names in `soak.bed` (their coupling and charge time from the
//! materials, [`StackLimits`]), the open-frame bound on the slowest decay and which decays
//! reach the surface there ([`open_frame_reach`]).

/// A bed's build, as a user names it in `soak.bed`: what its materials allow of its coupling
/// from thermistor to print surface, and how long its stack takes to charge.
///
/// G = 1/(R·A·q) in full power per K, where R is the stack's resistance per m² between the
/// thermistor and the surface, A the bed's area and q = P/A its heater's power per m²; and the
/// bed's whole heat capacity, in full power·s/K, is C = c·A/P = c/q with c its heat capacity per
/// m². Two bounds follow from the materials alone, per m² (see [`StackLimits`]):
/// - the weakest coupling such a build can have: G ≥ 1/(R_max·q_max), whatever the bed;
/// - for this bed, from its own heat-up (which gives C): G = C/(R·c) ≥ C/(R_max·c_max), the
///   "G ≈ 1/(τ × full-power heating rate)" of issue 29 with τ = R_max·c_max the build's
///   slowest stack time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BedPreset {
    /// The name in `soak.bed`.
    pub name: &'static str,
    /// What it is, in words.
    pub words: &'static str,
    /// Coupling G from the thermistor to the surface, full power per K: the weak end of such
    /// beds, 1/(R_max·q_max) (a weaker coupling waits longer).
    pub g: f64,
    /// R_max·c_max: the most the stack's resistance times the bed's heat capacity can be, s.
    pub rc_s: f64,
    /// What a layer behind the one a heat-up shows may add to R·c, s: a sheet on its magnet,
    /// whose own lag is a few seconds. None where the layer behind may be as slow as the one
    /// in front (glass over the plate) and merge with it: then the heat-up's lag tells nothing
    /// of the rest.
    pub hidden_s: Option<f64>,
    /// The stack's own charge time between thermistor and surface, s (the transient right
    /// after the bed reaches its band): its clamped time constants add up to at most
    /// Σ C_i·R_i ≤ R·C (see [`OPEN_FRAME_TAU_MAX_S`]), so `rc_s`.
    pub charge_s: f64,
}

/// Per-m² limits of real bed stacks, from their materials.
pub struct StackLimits;

impl StackLimits {
    /// Heater power per m², at most: 1 W/cm² (a 250 mm bed with a 625 W mains heater).
    pub const Q_MAX_W_M2: f64 = 10_000.0;
    /// Heat capacity per m², J/m²K: a 1.5 mm silicone pad (1.2 g/cm³, 1.3 J/gK) ...
    pub const C_PAD: f64 = 2_340.0;
    /// ... a 10 mm aluminium plate (2.7 g/cm³, 0.9 J/gK) ...
    pub const C_PLATE: f64 = 24_300.0;
    /// ... 0.8 mm spring steel (7.85, 0.46) with PEI on a 1 mm magnet sheet (3.6, 0.9) ...
    pub const C_STEEL: f64 = 2_890.0 + 3_240.0;
    /// ... or 5 mm borosilicate glass (2.23, 0.83).
    pub const C_GLASS: f64 = 9_250.0;
    /// Resistance per m², m²K/W: the pad's thermistor through 1 mm of silicone (0.3 W/mK) ...
    pub const R_PAD: f64 = 0.001 / 0.3;
    /// ... a 1 mm magnet sheet at 0.4 W/mK and half 0.5 mm of steel (20 W/mK) ...
    pub const R_STEEL: f64 = 0.001 / 0.4 + 0.000_25 / 20.0;
    /// ... glass on clips over an air gap of up to 0.4 mm (0.03 W/mK) and half 5 mm of glass
    /// (1.1 W/mK) ...
    pub const R_GLASS: f64 = 0.0004 / 0.03 + 0.0025 / 1.1;
    /// ... a bare plate's own half thickness and a 0.1 mm PEI film (0.22 W/mK).
    pub const R_BARE: f64 = 0.0005;
    /// The least a steel sheet on its magnet can add: a 1 mm magnet sheet at 1.2 W/mK and
    /// half 0.5 mm of steel.
    pub const R_STEEL_MIN: f64 = 0.001 / 1.2 + 0.000_25 / 20.0;
    /// The least glass on clips can add: a 0.05 mm air gap and half 3 mm of glass.
    pub const R_GLASS_MIN: f64 = 0.000_05 / 0.03 + 0.0015 / 1.1;
}

/// The beds `soak.bed` may name, strongest coupling first. The last is the weakest coupling,
/// assumed when the bed is neither identified nor named.
pub const BED_PRESETS: &[BedPreset] = &[
    preset(
        "bare-plate",
        "bare aluminium plate, thermistor in the plate",
        StackLimits::R_BARE,
        StackLimits::C_PAD + StackLimits::C_PLATE,
        Some(0.0),
    ),
    preset(
        "steel-plate",
        "steel sheet on a magnet, thermistor in the plate",
        StackLimits::R_STEEL,
        StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_STEEL,
        Some(
            StackLimits::R_STEEL
                * (StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_STEEL),
        ),
    ),
    preset(
        "bare-pad",
        "bare aluminium plate, thermistor in the heater pad",
        StackLimits::R_PAD + StackLimits::R_BARE,
        StackLimits::C_PAD + StackLimits::C_PLATE,
        Some(0.0),
    ),
    preset(
        "steel-pad",
        "steel sheet on a magnet, thermistor in the heater pad",
        StackLimits::R_PAD + StackLimits::R_STEEL,
        StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_STEEL,
        Some(
            StackLimits::R_STEEL
                * (StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_STEEL),
        ),
    ),
    preset(
        "glass-plate",
        "glass on clips, thermistor in the plate",
        StackLimits::R_GLASS,
        StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_GLASS,
        None,
    ),
    preset(
        "glass-pad",
        "glass on clips, thermistor in the heater pad",
        StackLimits::R_PAD + StackLimits::R_GLASS,
        StackLimits::C_PAD + StackLimits::C_PLATE + StackLimits::C_GLASS,
        None,
    ),
];

/// A preset from its stack's limits: resistance `r` m²K/W and heat capacity `c` J/m²K.
const fn preset(
    name: &'static str,
    words: &'static str,
    r: f64,
    c: f64,
    hidden_s: Option<f64>,
) -> BedPreset {
    BedPreset {
        name,
        words,
        g: 1.0 / (r * StackLimits::Q_MAX_W_M2),
        rc_s: r * c,
        hidden_s,
        charge_s: r * c,
    }
}

/// The slowest decay the rule rules out on an open frame (`soak.frame = "open"`), s: 20 min.
///
/// With the thermistor's node held, the bed is a network of heat capacities C_i joined by
/// conductances to that node and to the room; its slowest time constant is at most the trace
/// of K⁻¹C, Σ C_i R_i, where R_i is node i's resistance to ground (the held node or the room;
/// taking the room's path away only raises it). Per m², the slowest stacks of real beds:
/// - thermistor in a 1.5 mm silicone pad, 1 mm of silicone and 0.2 mm of adhesive (0.2 W/mK)
///   to the plate: R = 0.006 m²K/W; a 10 mm aluminium plate (24.3 kJ/m²K): 146 s;
/// - 1 mm magnet sheet (2.9 kJ/m²K) behind 0.2 mm of adhesive and half its 0.4 W/mK:
///   R = 0.0083, 24 s; a 1.5 mm steel sheet (5.4 kJ/m²K) on it with 0.002 m²K/W of contact,
///   R = 0.0115: 62 s; so 232 s (3.9 min) for steel on a magnet over a 10 mm plate;
/// - 5 mm glass (10.5 kJ/m²K) on clips over a 0.5 mm air gap (0.03 W/mK) and half its own
///   1 W/mK: R = 0.025, 264 s; with the plate 410 s (6.8 min);
/// - insulation under the pad: 6 mm cork (2.4 kJ/m²K, 0.04 W/mK, its underside at 5 W/m²K):
///   R = 0.086, 206 s; 10 mm of foam, 46 s.
///
/// The worst open stack (pad-sensed, 10 mm plate, 5 mm glass on a poor gap, cork) is thus at
/// most 616 s (10.3 min) however weak its convection (h only lowers R). Beside it, the
/// carriage or frame the bed is screwed to (a 6 mm aluminium Y plate of 250 mm, 0.9 kJ/K,
/// cooled on both faces at 5–10 W/m²K) settles in about 12 min, through spacers that carry a
/// few watts. Twice the stack's bound covers both: 20 min. Not covered: an enclosure, or a
/// frame built in a box (the air warms for hours: that is what `tau_max_s` is for).
pub const OPEN_FRAME_TAU_MAX_S: f64 = 1200.0;

/// On an open frame, the air over the print surface is the room's, renewed by convection in
/// seconds, and the small parts beside the bed (clips, the frame's nearest extrusion) follow
/// within minutes: decays up to this long may be the air and parts the surface loses heat to,
/// s (5 min). The bench's open frames' air and frame settle in 1–2.5 min.
pub const OPEN_AIR_TAU_S: f64 = 300.0;

/// Which decays reach the print surface on an open frame (`soak.frame = "open"`), and how much
/// of their power.
///
/// With the thermistor's node held, a decay is a part of the bed or its surroundings warming
/// towards its final temperature. Those as fast as the bed stack's own charge (at most its
/// R·C, [`BedPreset::charge_s`]) or as the open air over it ([`OPEN_AIR_TAU_S`]) may be the
/// stack between thermistor and surface, or the air the surface loses heat to: their power
/// flows through the surface and it warms by ΔP / G, all of it. On an open frame, what is
/// slower than both is the carriage or frame the bed is mounted on (see
/// [`OPEN_FRAME_TAU_MAX_S`]), which draws its heat from the plate or the pad, not through the
/// surface:
/// - thermistor in the plate: the plate is held, so the carriage's warming changes the power
///   and not the surface: weight 0;
/// - thermistor in the pad: the plate, and the surface on it, warm by ΔP times the pad's
///   resistance to the plate, while G counts the whole stack's: the share of ΔP / G that
///   reaches the surface is R_pad / (R_pad + R_surface side), at most with the thickest pad
///   ([`StackLimits::R_PAD`]) under the best-conducting surface layer the build allows
///   (`steel-pad` 0.80, `glass-pad` 0.52, `bare-pad` or a bed not named: all of it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceReach {
    /// Decays up to this long reach the surface whole, s.
    pub whole_s: f64,
    /// The share of a slower decay's ΔP / G that reaches the surface (0–1).
    pub slow_share: f64,
}

/// The open frame's [`SurfaceReach`] for the build `bed` names (`soak.bed`) and a stack whose
/// charge time is `charge_s`. None unless `frame` is "open" (in an enclosure the air over the
/// surface warms for hours, and every decay may reach it).
#[must_use]
pub fn open_frame_reach(frame: &str, bed: &str, charge_s: f64) -> Option<SurfaceReach> {
    if frame != "open" {
        return None;
    }
    let pad_share = |r_surface_min: f64| StackLimits::R_PAD / (StackLimits::R_PAD + r_surface_min);
    let slow_share = match bed {
        "bare-plate" | "steel-plate" | "glass-plate" => 0.0,
        "steel-pad" => pad_share(StackLimits::R_STEEL_MIN),
        "glass-pad" => pad_share(StackLimits::R_GLASS_MIN),
        _ => 1.0,
    };
    Some(SurfaceReach {
        whole_s: charge_s.max(OPEN_AIR_TAU_S),
        slow_share,
    })
}

/// Thermal expansion that turns surface kelvin into µm per 100 mm: steel and aluminium.
pub const UM_PER_100MM_K_STEEL: f64 = 1.2;
/// See [`UM_PER_100MM_K_STEEL`].
pub const UM_PER_100MM_K_ALUMINIUM: f64 = 2.3;

/// Kelvin of surface warming in words with what they cost in µm/100 mm.
#[must_use]
pub fn kelvin_words(k: f64) -> String {
    format!(
        "{k:.1} K ({:.1} µm/100 mm on steel, {:.1} on aluminium)",
        k * UM_PER_100MM_K_STEEL,
        k * UM_PER_100MM_K_ALUMINIUM
    )
}

/// What printing now costs, in words a user weighs: "about 1.5 K, 2 µm per 100 mm on steel"
/// (the 95 % figure, rounded as a person reads it: tenths below 10 K, whole kelvin above, the
/// expansion to a whole µm from 2 µm on).
#[must_use]
pub fn cost_words(k: f64) -> String {
    if !k.is_finite() || k < 0.05 {
        return "less than 0.1 K".into();
    }
    let kelvin = if k < 10.0 {
        format!("{k:.1}")
    } else {
        format!("{k:.0}")
    };
    let um = k * UM_PER_100MM_K_STEEL;
    let um = if um < 2.0 {
        format!("{um:.1}")
    } else {
        format!("{um:.0}")
    };
    format!("about {kelvin} K, {um} µm per 100 mm on steel")
}

#[cfg(test)]
mod tests {
    use super::cost_words;

    #[test]
    fn a_cost_is_said_as_a_person_weighs_it() {
        assert_eq!(cost_words(1.5), "about 1.5 K, 1.8 µm per 100 mm on steel");
        assert_eq!(cost_words(1.7), "about 1.7 K, 2 µm per 100 mm on steel");
        assert_eq!(cost_words(34.6), "about 35 K, 42 µm per 100 mm on steel");
        assert_eq!(cost_words(0.01), "less than 0.1 K");
        assert_eq!(cost_words(f64::NAN), "less than 0.1 K");
    }
}
