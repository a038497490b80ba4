//! The operations every daemon answers besides the calibrations' own ([`CORE_OPS`]), and
//! their call typed at the boundary ([`CoreCall`]).

use super::table::{arg, ArgKind, ArgSpec, Echo, Op, OpSpec};

const REASON: ArgSpec = arg(
    "reason",
    ArgKind::Text,
    "aborted",
    "a word or a quoted text",
    "",
    "why, noted in the session (optional)",
);
const SURFACE: ArgSpec = arg(
    "surface",
    ArgKind::Choice(crate::calib::soak::ask::SURFACE_WORDS),
    "steel",
    "steel, glass, bare or unknown",
    "",
    "what is on the bed: a steel sheet on a magnet, glass, the bare plate",
);
const SENSOR: ArgSpec = arg(
    "sensor",
    ArgKind::Choice(crate::calib::soak::ask::SENSOR_WORDS),
    "pad",
    "plate, pad or unknown",
    "",
    "where the bed's thermistor is: in the plate or in the heater pad",
);
const FRAME: ArgSpec = arg(
    "frame",
    ArgKind::Choice(crate::calib::soak::ask::FRAME_WORDS),
    "open",
    "open, enclosed or unknown",
    "",
    "open: no enclosure; enclosed: in an enclosure or a box",
);

const SAY_MSG: ArgSpec = arg(
    "msg",
    ArgKind::Text,
    "first␤second",
    "a quoted text, lines separated by ␤",
    "",
    "the lines to say",
);

const ONLINE_SECONDS: ArgSpec = arg(
    "seconds",
    ArgKind::Whole { min: 0, max: 3600 },
    "30",
    "0..3600",
    "0",
    "for how long from now the service answers (0: it stopped)",
);

/// The operations every daemon answers besides the calibrations' own.
pub static CORE_OPS: &[Op<CoreCall>] = &[
    Op {
        spec: OpSpec {
            by_agent: true,
            ..OpSpec::remote(
                "klipcal_status",
                "KLIPCAL_STATUS",
                "status",
                "show the daemon's state and what it sees of the printer",
                &[],
            )
        },
        parse: |_| Ok(CoreCall::Status),
    },
    Op {
        spec: OpSpec {
            echo: Some(Echo {
                fallback: "cancelled",
                note: "cancelled from klipcal's page",
            }),
            ..OpSpec::remote(
                "klipcal_cancel",
                "KLIPCAL_CANCEL",
                "cancel",
                "cancel the calibration session (cancels its print, turns the heaters off)",
                &[REASON],
            )
        },
        parse: |a| {
            Ok(CoreCall::Cancel(
                a.text(&REASON)
                    .unwrap_or_else(|| "cancelled by the user".into()),
            ))
        },
    },
    Op {
        spec: OpSpec::local(
            "_KLIPCAL_CANCEL_ASK",
            "ask before ending the session (the Cancel of klipcal's dialogs)",
            &[],
            &[
                // What ending does is in the title, not a text row of its own (issue 40 item
                // 6: the question is asked twice a round when Back is pressed once).
                "RESPOND TYPE=command MSG=\"action:prompt_begin end the session? (heaters off)\"",
                // The Yes answers the question of the dialog whose Cancel asked (its ASK):
                // klipcal refuses it once that question has passed (issue 40).
                "RESPOND TYPE=command MSG=\"action:prompt_button Yes, end the session|KLIPCAL_CANCEL{' ASK=%d' % (params.ASK|int) if 'ASK' in params else ''}|error\"",
                "RESPOND TYPE=command MSG=\"action:prompt_footer_button Back|_KLIPCAL_PROMPT_BACK|info\"",
                "RESPOND TYPE=command MSG=\"action:prompt_show\"",
            ],
        ),
        parse: |_| Err(anyhow::anyhow!("_KLIPCAL_CANCEL_ASK runs in Klipper")),
    },
    Op {
        spec: OpSpec::local(
            crate::jobs::core::console::SAY_MACRO,
            "say an answer of several lines as one console row (klipcal sends it; MSG's lines end at ␤)",
            &[SAY_MSG],
            &["{action_respond_info(\"klipcal \" ~ (params.MSG|default(\"\"))|replace(\"␤\", \"\\n\"))}"],
        ),
        parse: |_| Err(anyhow::anyhow!("_KLIPCAL_SAY runs in Klipper")),
    },
    Op {
        spec: OpSpec {
            variables: &[("on", "0")],
            ..OpSpec::local(
                crate::moonraker::ONLINE_MACRO,
                "the klipcal service answers for SECONDS more (klipcal sends it every few seconds; meanwhile its macros do not say \"asking the klipcal service...\"; _KLIPCAL_OFFLINE ends it)",
                &[ONLINE_SECONDS],
                &[
                    "{% set s = params.SECONDS|default(0)|int(-1) %}",
                    "{% if s < 0 or s > 3600 %}",
                    "{action_raise_error(\"_KLIPCAL_ONLINE: SECONDS=\" ~ params.SECONDS ~ \" is not a whole number of seconds from 0 to 3600\")}",
                    "{% endif %}",
                    "SET_GCODE_VARIABLE MACRO=_KLIPCAL_ONLINE VARIABLE=on VALUE={1 if s > 0 else 0}",
                    "UPDATE_DELAYED_GCODE ID=_KLIPCAL_OFFLINE DURATION={s}",
                ],
            )
        },
        parse: |_| Err(anyhow::anyhow!("_KLIPCAL_ONLINE runs in Klipper")),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_soak_bed",
            "KLIPCAL_SOAK_BED",
            "soak/bed",
            "answer the bed soak's question (written to klipcal.toml, used at once): SURFACE=steel, glass or bare, SENSOR=plate or pad (where the bed's thermistor is), FRAME=open or enclosed; unknown keeps the slow assumption",
            &[SURFACE, SENSOR, FRAME],
        ),
        parse: |a| {
            Ok(CoreCall::SoakBed(super::soak_ask::BuildAnswer::from_words(
                a.choice(&SURFACE)?,
                a.choice(&SENSOR)?,
                a.choice(&FRAME)?,
            )?))
        },
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_prompt_back",
            "_KLIPCAL_PROMPT_BACK",
            "prompt/back",
            "back to klipcal's dialog (from the cancel question)",
            &[],
        ),
        parse: |_| Ok(CoreCall::PromptBack),
    },
    Op {
        spec: OpSpec::remote(
            "klipcal_prompt_close",
            "_KLIPCAL_PROMPT_CLOSE",
            "prompt/close",
            "close klipcal's dialog (then type readings on the console)",
            &[],
        ),
        parse: |_| Ok(CoreCall::PromptClose),
    },
];

/// A call of the common operations, typed at the boundary.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CoreCall {
    /// `klipcal_status` (answered by the agent, around [`crate::jobs::Calibrations::status`]).
    Status,
    /// `klipcal_cancel` with its reason.
    Cancel(String),
    /// `klipcal_soak_bed`: an answer to the soak question.
    SoakBed(super::soak_ask::BuildAnswer),
    /// `klipcal_prompt_back`.
    PromptBack,
    /// `klipcal_prompt_close`.
    PromptClose,
}
