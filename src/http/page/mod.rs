//! The page: server-rendered HTML from the status document (the same JSON `/api/status`
//! answers), with a small inline script that polls the status, validates readings live
//! through `/api/ab/check` and posts the forms as JSON. No build step, no external resources
//! (printer hosts are often offline), fits a phone. Every text from a document is escaped.

use std::fmt::Write as _;

use serde_json::Value;

/// Escapes text for HTML content and attribute values.
fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

fn text(v: &Value) -> String {
    match v {
        Value::String(s) => esc(s),
        Value::Null => String::new(),
        other => esc(&other.to_string()),
    }
}

/// A distance with at most 3 decimals (as the console shows it).
fn mm(v: f64) -> String {
    crate::calib::entry::fmt_mm(v)
}

const STYLE: &str = r#"
*{box-sizing:border-box}body{font:15px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;background:#f1f3f5;color:#212529}
header{background:#212529;color:#f8f9fa;padding:.6em 1em;display:flex;gap:1em;align-items:baseline;flex-wrap:wrap}
header h1{font-size:1.15em;margin:0}main{max-width:980px;margin:0 auto;padding:.6em}
section{background:#fff;border-radius:8px;padding:.8em 1em;margin:.7em 0;box-shadow:0 1px 2px #0001}
h2{font-size:1.05em;margin:.1em 0 .5em}.state{display:inline-block;padding:.05em .5em;border-radius:1em;background:#e7f5ff;color:#1864ab;font-weight:600}
.state.failed,.state.cancelled{background:#fff5f5;color:#c92a2a}.state.converged,.state.applied{background:#ebfbee;color:#2b8a3e}
fieldset{border:1px solid #dee2e6;border-radius:6px;margin:.5em 0;padding:.5em .7em}legend{font-weight:600}
.fields{display:flex;flex-wrap:wrap;gap:.4em}.field{display:flex;flex-direction:column;width:7.5em}
input{font:inherit;padding:.35em .4em;border:1px solid #adb5bd;border-radius:4px;width:100%}
input[aria-invalid=true]{border-color:#e03131;background:#fff5f5}.err{color:#c92a2a;font-size:.8em;min-height:1em}
.msg{margin:.3em 0}.msg.error{color:#c92a2a}.msg.ok{color:#2b8a3e}
button{font:inherit;padding:.35em .9em;border-radius:4px;border:1px solid #1c7ed6;background:#1c7ed6;color:#fff;cursor:pointer}
button.quiet{background:#fff;color:#1c7ed6}button.danger{background:#fff;color:#c92a2a;border-color:#c92a2a}
button:disabled{opacity:.5;cursor:default}.row{display:flex;gap:.6em;flex-wrap:wrap;align-items:center}
table{border-collapse:collapse;width:100%}td,th{text-align:left;padding:.2em .4em;border-bottom:1px solid #e9ecef}
img.plot,.diagram svg{width:100%;height:auto;max-height:70vh}.diagram .pair.hl line{stroke:#e03131;stroke-width:1.2}
.diagram .pair.hl text{fill:#c92a2a;font-weight:700}#banner{display:none;background:#fff3bf;padding:.5em 1em}
.snap{position:relative;line-height:0;overflow:hidden}.stage{position:relative;transform-origin:0 0}
.snap img{width:100%;height:auto;display:block}.snap svg{position:absolute;left:0;top:0;width:100%;height:100%}
figure[data-click="1"] .snap{cursor:crosshair;outline:3px solid #2b8a3e}#clicked circle{fill:none;stroke:#2b8a3e;stroke-width:2}.snap svg *{vector-effect:non-scaling-stroke}
#found circle,#found line{fill:none;stroke:#e03131;stroke-width:2}.approach.plus{fill:#1c7ed6}.approach.minus{fill:#f76707}
figure{margin:.4em 0}figcaption{font-size:.9em}
.saved{color:#495057;font-size:.9em}.scroll{overflow-x:auto}small{color:#495057}
@media (max-width:600px){main{padding:.3em}section{padding:.6em .5em}td,th{padding:.2em .25em;font-size:.88em}}
"#;

const SCRIPT: &str = r#"
const $=(s,e=document)=>e.querySelector(s),$$=(s,e=document)=>[...e.querySelectorAll(s)];
async function call(op,body){
  const r=await fetch('/api/'+op,{method:'POST',headers:{'Content-Type':'application/json'},body:JSON.stringify(body||{})});
  let j;try{j=await r.json()}catch(e){j={ok:false,error:{message:'HTTP '+r.status}}}
  return j;
}
function say(el,msg,ok){if(!el)return;el.textContent=msg||'';el.className='msg '+(ok?'ok':'error')}
function entries(fs){return $$('input.reading',fs)}
let timers={};
async function check(fs,keep){
  const pair=fs.dataset.pair,inputs=entries(fs),filled=inputs.filter(i=>i.value.trim()!=='');
  inputs.forEach(i=>{if(i.value.trim()===''){i.removeAttribute('aria-invalid');$('.err',i.parentNode).textContent=''}});
  if(!filled.length){say($('.msg',fs),'');return}
  const j=await call('ab/check',{pair,values:inputs.map(i=>i.value.trim())});
  if(j.ok===false){say($('.msg',fs),j.error.message,false);return}
  inputs.forEach((inp,k)=>{if(inp.value.trim()==='')return;const it=(j.items||[])[k]||{};const bad=!!it.error;
    inp.setAttribute('aria-invalid',bad?'true':'false');$('.err',inp.parentNode).textContent=bad?it.error.replace(/ for \S+ \(nominal [^)]*\); measure outer face to outer face/,''):''});
  if(!keep)say($('.msg',fs),j.valid?'':j.message,j.valid);
}
let dirty=false;
$$('fieldset.pair').forEach(fs=>{
  entries(fs).forEach(i=>{
    i.addEventListener('input',()=>{dirty=true;clearTimeout(timers[fs.dataset.pair]);timers[fs.dataset.pair]=setTimeout(()=>check(fs),300)});
    i.addEventListener('focus',()=>{$$('.diagram .pair').forEach(g=>g.classList.toggle('hl',g.dataset.pair===fs.dataset.pair))});
  });
  const save=$('button.save',fs);
  if(save)save.addEventListener('click',async ev=>{ev.preventDefault();
    const values=entries(fs).map(i=>i.value.trim());
    const j=await call('ab/measure',{pair:fs.dataset.pair,values});
    if(j.ok){dirty=false;say($('.msg',fs),j.message,true);setTimeout(()=>location.reload(),400)}
    else{say($('.msg',fs),j.error.message,false);check(fs,true)}});
  const clear=$('button.clear',fs);
  if(clear)clear.addEventListener('click',async ev=>{ev.preventDefault();
    if(!confirm('Remove every saved reading of '+fs.dataset.pair+'?'))return;
    const j=await call('ab/clear',{pair:fs.dataset.pair});
    if(j.ok)location.reload();else say($('.msg',fs),j.error.message,false)});
});
$$('button[data-op]').forEach(b=>b.addEventListener('click',async ev=>{ev.preventDefault();
  if(b.dataset.confirm&&!confirm(b.dataset.confirm))return;
  let body={};const f=b.closest('form');
  if(f)$$('[name]',f).forEach(i=>{if(i.type==='checkbox'){if(i.checked)body[i.name]=1}else if(i.value!=='')body[i.name]=i.value});
  b.disabled=true;const j=await call(b.dataset.op,body);b.disabled=false;
  const out=$('#'+b.dataset.out)||$('#opmsg');
  if(j.ok){say(out,j.message||'done',true);setTimeout(()=>location.reload(),600)}else say(out,j.error.message,false)}));
const sig=document.body.dataset.sig;
async function poll(){
  try{const r=await fetch('/api/status');const j=await r.json();const s=j.session||{};
    const now=[s.id,s.state,s.round,JSON.stringify(s.readings||{}),Object.values(s.camera||{}).reduce((n,c)=>n+(c.cycles||[]).length,0)].join('|');
    const f=s.snapshot,fig=$('#snapshot');
    if(f&&!fig&&!dirty)location.reload();
    if(f&&fig&&(f.click||fig.dataset.click==='1')&&(String(f.seq)!==fig.dataset.seq||(f.click?'1':'0')!==fig.dataset.click)&&!dirty)location.reload();
    if(f&&fig&&String(f.seq)!==fig.dataset.seq){fig.dataset.seq=String(f.seq);$('#snapimg').src='/api/backlash/snapshot.jpg?seq='+f.seq;
      const g=$('#found'),c=f.centre_px;g.style.display=c?'':'none';if(c)g.setAttribute('transform','translate('+(c[0]+.5)+' '+(c[1]+.5)+')');
      $('#snapcap').textContent=f.refused?f.what+': no reading, '+f.refused:(c?f.what+': nozzle at ('+c[0].toFixed(2)+', '+c[1].toFixed(2)+') px ± '+f.uncertainty_px.toFixed(2)+' px':f.what)}
    const p=$('#progress');if(p&&s.progress!==undefined)p.textContent=s.progress;
    const k=$('#klippy');if(k&&j.connection)k.textContent=j.connection.klippy_state||j.connection.moonraker;
    if(now!==sig){if(dirty)$('#banner').style.display='block';else location.reload()}
  }catch(e){}
}
setInterval(poll,3000);
// The click-in-snapshot flow: a click on the picture is the nozzle's tip in the picture's
// pixels (pixel centres at whole numbers), whatever the zoom; without a zoom yet, a first
// click zooms in there.
const fig=$('#snapshot');
if(fig&&fig.dataset.click==='1'){
  const img=$('#snapimg'),stage=$('.stage',fig);let ZOOM=+(fig.dataset.zoom||4);
  let at=fig.dataset.hint?fig.dataset.hint.split(',').map(Number):null;
  const view=()=>{if(!at){stage.style.transform='';return}
    const W=stage.clientWidth,H=stage.clientHeight,k=W/img.naturalWidth;
    stage.style.transform='translate('+(W/2-ZOOM*(at[0]+.5)*k)+'px,'+(H/2-ZOOM*(at[1]+.5)*k)+'px) scale('+ZOOM+')'};
  const ready=()=>{view();fig.dataset.ready='1'};
  if(img.complete&&img.naturalWidth)ready();else img.addEventListener('load',ready);
  const whole=$('#wholepic');if(whole)whole.addEventListener('click',ev=>{ev.preventDefault();at=null;ZOOM=4;view()});
  $('.snap',fig).addEventListener('click',async ev=>{
    if(fig.dataset.sent)return;
    const r=img.getBoundingClientRect(),k=img.naturalWidth/r.width;
    const x=(ev.clientX-r.left)*k-.5,y=(ev.clientY-r.top)*k-.5;
    if(!at){at=[x,y];view();say($('#clickhelp'),'Now click the tip exactly (zoomed in).',true);return}
    fig.dataset.sent='1';
    const c=$('#clicked');c.setAttribute('transform','translate('+(x+.5)+' '+(y+.5)+')');c.style.display='';
    const j=await call('backlash/tip',{x:+x.toFixed(3),y:+y.toFixed(3),frame:+fig.dataset.seq,sd:+Math.max(k*(ev.pointerType==='touch'?3:1),0.05).toFixed(3)});
    if(j.ok){say($('#clickhelp'),j.message,true);setInterval(poll,600)}
    else{delete fig.dataset.sent;c.style.display='none';say($('#clickhelp'),j.error.message,false)}});
}
const soak=$('#soak');if(soak)setInterval(()=>{soak.src='/api/plots/soak.svg?t='+Date.now()},15000);
"#;

/// The signature the script compares with each poll to know when to reload.
fn signature(session: &Value) -> String {
    if session.is_null() {
        return "|||{}|0".into();
    }
    let readings = if session["readings"].is_null() {
        "{}".to_string()
    } else {
        session["readings"].to_string()
    };
    let camera_cycles: usize = session["camera"].as_object().map_or(0, |o| {
        o.values()
            .filter_map(|c| c["cycles"].as_array())
            .map(Vec::len)
            .sum()
    });
    format!(
        "{}|{}|{}|{}|{camera_cycles}",
        session["id"]
            .as_i64()
            .map(|v| v.to_string())
            .unwrap_or_default(),
        session["state"].as_str().unwrap_or(""),
        session["round"]
            .as_i64()
            .map(|v| v.to_string())
            .unwrap_or_default(),
        readings
    )
}

/// The whole page for a status answer (`{"ok", "session", "last", …}` or an error) and, while
/// readings are taken, the layout diagram.
#[must_use]
pub(crate) fn render(status: &Value, diagram_svg: Option<&str>) -> String {
    let session = status.get("session").cloned().unwrap_or(Value::Null);
    let mut h = String::new();
    let _ = write!(
        h,
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width,initial-scale=1\">\
         <title>klipcal</title><style>{STYLE}</style></head><body data-sig=\"{}\">",
        esc(&signature(&session))
    );
    let klippy = status["connection"]["klippy_state"]
        .as_str()
        .or_else(|| status["connection"]["moonraker"].as_str())
        .unwrap_or("unknown");
    let _ = write!(
        h,
        "<header><h1>klipcal</h1><span>Klipper: <b id=\"klippy\">{}</b></span>{}</header>\
         <div id=\"banner\">The session moved on. <a href=\"/\">Reload</a> (your unsaved \
         entries stay until you do).</div><main>",
        esc(klippy),
        status["daemon"]["version"]
            .as_str()
            .map(|v| format!("<small>v{}</small>", esc(v)))
            .unwrap_or_default()
    );
    if status["ok"] == Value::Bool(false) {
        let _ = write!(
            h,
            "<section><h2>Status unavailable</h2><p class=\"msg error\">{}</p></section>",
            text(&status["error"]["message"])
        );
    }
    if let Some(msg) = status["connection"]["message"].as_str() {
        // Moonraker unreachable: said at once; the session below still shows from the database.
        let _ = write!(
            h,
            "<p id=\"moonraker\" class=\"msg error\">{}</p>",
            esc(msg)
        );
    }
    h.push_str("<p id=\"opmsg\" class=\"msg\"></p>");
    let active = session["state"]
        .as_str()
        .is_some_and(|s| !matches!(s, "converged" | "failed" | "cancelled"));
    if session.is_null() || !active {
        start_form(&mut h);
    }
    if !session.is_null() {
        session_card(&mut h, &session, active);
        if session["kind"] == "ab" {
            ab_sections(&mut h, &session, diagram_svg);
        }
        if session["kind"] == "mesh" {
            mesh_section(&mut h, &session);
        }
        if session["kind"] == "backlash" {
            backlash_section(&mut h, &session);
        }
    }
    last_results(&mut h, &status["last"], &session);
    operations(&mut h, &crate::jobs::registry::all_ops());
    let _ = write!(h, "</main><script>{SCRIPT}</script></body></html>");
    h
}

/// Every operation of the command table as a form, with a field per argument (its help as the
/// field's hint, its choices as a list): whatever a macro can do, the page can (a phone without
/// a console reaches all of them). Folded away under the session's own controls.
fn operations(h: &mut String, ops: &[&crate::jobs::table::OpSpec]) {
    use crate::jobs::table::{arg_form, ArgKind};
    h.push_str(
        "<section id=\"operations\"><details><summary><b>Every operation</b> \
         <small>(the same as the macros)</small></summary>",
    );
    for op in ops {
        let Some(path) = op.http else { continue };
        let _ = write!(
            h,
            "<form class=\"op\" data-path=\"{}\"><p><b>{}</b> <small>{}</small></p><div class=\"fields\">",
            esc(path),
            esc(op.macro_name),
            esc(op.summary)
        );
        for a in op.args {
            let name = esc(a.name);
            let label = esc(&a.name.to_uppercase());
            let hint = esc(&format!("{} ({})", a.help, arg_form(a)));
            match a.kind {
                ArgKind::Choice(choices) => {
                    let _ = write!(
                        h,
                        "<label class=\"field\" title=\"{hint}\">{label}<select name=\"{name}\">\
                         <option value=\"\">{}</option>",
                        if a.default.is_empty() {
                            "default".to_string()
                        } else {
                            format!("default ({})", esc(a.default))
                        }
                    );
                    for c in choices {
                        let _ = write!(h, "<option>{}</option>", esc(c));
                    }
                    h.push_str("</select></label>");
                }
                ArgKind::Flag => {
                    let _ = write!(
                        h,
                        "<label class=\"field\" title=\"{hint}\"><span>{label}</span>\
                         <input type=\"checkbox\" name=\"{name}\" style=\"width:auto\"></label>"
                    );
                }
                _ => {
                    let _ = write!(
                        h,
                        "<label class=\"field\" title=\"{hint}\">{label}<input name=\"{name}\" \
                         placeholder=\"{}\" autocomplete=\"off\"></label>",
                        esc(a.example)
                    );
                }
            }
        }
        let _ = write!(
            h,
            "</div><p class=\"row\"><button class=\"quiet\" data-op=\"{}\" data-out=\"op-{}\" \
             data-confirm=\"Run {} now?\">Run</button><span id=\"op-{}\" class=\"msg\"></span></p></form>",
            esc(path),
            esc(&path.replace('/', "-")),
            esc(op.macro_name),
            esc(&path.replace('/', "-"))
        );
    }
    h.push_str("</details></section>");
}

fn start_form(h: &mut String) {
    h.push_str(
        "<section><h2>Start an A/B calibration</h2><form class=\"row\" id=\"start\">\
         <label>Bed °C <input name=\"bed\" inputmode=\"decimal\" placeholder=\"60\" size=\"4\" style=\"width:5em\"></label>\
         <label>Nozzle °C <input name=\"extruder\" inputmode=\"decimal\" placeholder=\"215\" style=\"width:5em\"></label>\
         <label>Layout <select name=\"layout\"><option value=\"\">default</option><option>paper</option><option>full</option></select></label>\
         <button data-op=\"ab/start\" data-out=\"startmsg\" data-confirm=\"Print the pylon job now? The bed heats and the printer moves.\">Start</button>\
         </form><p id=\"startmsg\" class=\"msg\"></p>\
         <p class=\"row\"><button class=\"quiet\" data-op=\"mesh/capture\" data-out=\"startmsg\" \
         data-confirm=\"Start a thermal mesh capture? The bed heats and the printer probes meshes for up to mesh.max_s.\">\
         Capture a thermal mesh</button></p></section>",
    );
}

fn session_card(h: &mut String, s: &Value, active: bool) {
    let state = s["state"].as_str().unwrap_or("?");
    let kind = match s["kind"].as_str() {
        Some("ab") => "A/B calibration",
        Some("backlash") => "backlash measurement",
        Some("mesh") => "thermal mesh",
        _ => "calibration",
    };
    let _ = write!(
        h,
        "<section id=\"session\"><h2>{kind} · session {} · round {} <span class=\"state {}\">{}</span></h2>\
         <p id=\"progress\">{}</p>",
        text(&s["id"]),
        text(&s["round"]),
        esc(state),
        esc(state),
        text(&s["progress"])
    );
    if let Some(r) = s["reason"].as_str() {
        let _ = write!(h, "<p class=\"msg error\">{}</p>", esc(r));
    }
    if let Some(notes) = s["notes"].as_array().filter(|n| !n.is_empty()) {
        h.push_str("<details><summary>Notes</summary><ul>");
        for n in notes {
            let _ = write!(h, "<li>{}</li>", text(n));
        }
        h.push_str("</ul></details>");
    }
    if active {
        h.push_str(
            "<p class=\"row\"><button class=\"danger\" data-op=\"cancel\" data-confirm=\"Cancel the session? \
             A running print is cancelled and the heaters go off.\">Cancel session</button></p>",
        );
    }
    h.push_str("</section>");
}

fn ab_sections(h: &mut String, s: &Value, diagram_svg: Option<&str>) {
    let state = s["state"].as_str().unwrap_or("");
    if matches!(state, "heating" | "soaking" | "printing" | "holding") {
        h.push_str(
            "<section><h2>Bed</h2><img id=\"soak\" class=\"plot\" alt=\"bed temperature and power\" \
             src=\"/api/plots/soak.svg\"></section>",
        );
    }
    if matches!(state, "measuring" | "solved") {
        readings_form(h, s, diagram_svg);
    }
    if state == "solved" {
        solution(h, s);
    }
    rounds_table(h, s);
}

fn mesh_section(h: &mut String, s: &Value) {
    let state = s["state"].as_str().unwrap_or("");
    h.push_str("<section id=\"mesh\"><h2>Thermal mesh</h2>");
    if matches!(state, "soaking" | "capturing") {
        h.push_str(
            "<img id=\"soak\" class=\"plot\" alt=\"bed temperature and power\" src=\"/api/plots/soak.svg\">",
        );
    }
    let frames: Vec<String> = s["frame_c"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(Value::as_f64)
        .map(|t| format!("{t:.2}"))
        .collect();
    let _ = write!(
        h,
        "<p>{} mesh(es){}</p>",
        frames.len(),
        if frames.is_empty() {
            String::new()
        } else {
            format!(" at frame {} °C", esc(&frames.join(", ")))
        }
    );
    let r = &s["result"];
    if !r.is_null() {
        let n = r["profiles_c"].as_array().map_or(0, Vec::len);
        let _ = write!(
            h,
            "<p>model <b>{}</b>; {n} profiles klipcal_* over {}–{} °C; worst step {} µm</p>",
            text(&r["model"]),
            r["range_c"][0]
                .as_f64()
                .map(|v| format!("{v:.2}"))
                .unwrap_or_default(),
            r["range_c"][1]
                .as_f64()
                .map(|v| format!("{v:.2}"))
                .unwrap_or_default(),
            r["max_quantisation_um"]
                .as_f64()
                .map(|v| format!("{v:.1}"))
                .unwrap_or_default()
        );
        h.push_str("<div class=\"scroll\"><table><tr><th>model</th><th>max µm</th><th>mean µm</th><th>RMS µm</th></tr>");
        for m in r["models"].as_array().into_iter().flatten() {
            let f = |k: usize| m[k].as_f64().map(|v| format!("{v:.1}")).unwrap_or_default();
            let _ = write!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                text(&m[0]),
                f(1),
                f(2),
                f(3)
            );
        }
        if let Some(v) = r["vgb"].as_array() {
            let f = |k: usize| {
                v.get(k)
                    .and_then(Value::as_f64)
                    .map(|x| format!("{x:.1}"))
                    .unwrap_or_default()
            };
            let _ = write!(
                h,
                "<tr><td>VGB two-mesh</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                f(0),
                f(1),
                f(2)
            );
        }
        h.push_str("</table></div><p class=\"row\"><button data-op=\"mesh/follow\">Follow the frame</button>\
            <button class=\"quiet\" data-op=\"mesh/check\">Check against the bed</button></p>");
    }
    let f = &s["follow"];
    if f["following"] == Value::Bool(true) {
        let _ = write!(
            h,
            "<p>following: frame {} °C, profile {}, residual {} µm</p>",
            f["frame_c"]
                .as_f64()
                .map(|v| format!("{v:.2}"))
                .unwrap_or_default(),
            text(&f["loaded"]),
            f["residual_um"]
                .as_f64()
                .map(|v| format!("{v:.1}"))
                .unwrap_or_default()
        );
    } else if let Some(why) = f["stopped"].as_str() {
        let _ = write!(
            h,
            "<p class=\"msg error\">following stopped: {}</p>",
            esc(why)
        );
    }
    h.push_str("</section>");
}

fn backlash_section(h: &mut String, s: &Value) {
    h.push_str("<section id=\"backlash\"><h2>Backlash</h2>");
    if let Some(axis) = s["axis"].as_str() {
        let _ = write!(
            h,
            "<p>measuring {} — cycle {}: use the prompt's jog buttons (or _KLIPCAL_BACKLASH_JOG) \
             while looking through the camera</p>",
            esc(axis),
            text(&s["cycle"])
        );
    }
    if s["snapshot"].is_object() {
        snapshot_figure(h, s);
    }
    if let Some(reports) = s["camera"].as_object() {
        for (key, rep) in reports {
            camera_cycles(h, key, rep, &s["results"][key.as_str()]);
        }
    }
    if let Some(results) = s["results"].as_object().filter(|r| !r.is_empty()) {
        h.push_str(
            "<div class=\"scroll\"><table><tr><th>axis</th><th>backlash mm</th><th>± mm</th>\
             <th>spread mm</th><th>cycles</th><th>compensate</th><th>smooth_time s</th></tr>",
        );
        for (axis, r) in results {
            let f = |k: &str, d: usize| {
                r[k].as_f64()
                    .map(|v| format!("{v:.d$}"))
                    .unwrap_or_default()
            };
            let _ = write!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                esc(axis),
                f("backlash_mm", 3),
                f("uncertainty_mm", 3),
                f("spread_mm", 3),
                text(&r["cycles"]),
                if r["compensate"] == Value::Bool(true) { "yes" } else { "no" },
                f("smooth_time_s", 4)
            );
        }
        h.push_str("</table></div>");
        if s["state"] == "measured" {
            h.push_str(
                "<p class=\"row\"><button data-op=\"backlash/apply\" data-confirm=\"Set the measured \
                 backlash compensation and write it to the config (Klipper restarts)?\">Apply</button></p>",
            );
        }
    }
    h.push_str("</section>");
}

/// A number of px with 2 decimals.
fn px(v: &Value) -> String {
    v.as_f64().map(|x| format!("{x:.2}")).unwrap_or_default()
}

/// The caption of a camera frame: where it was taken, and what detection found (the script
/// builds the same words when a newer frame comes).
fn snapshot_caption(f: &Value) -> String {
    match f["refused"].as_str() {
        Some(why) => format!("{}: no reading, {why}", text(&f["what"])),
        None if f["centre_px"].is_array() => format!(
            "{}: nozzle at ({}, {}) px ± {} px",
            text(&f["what"]),
            px(&f["centre_px"][0]),
            px(&f["centre_px"][1]),
            px(&f["uncertainty_px"])
        ),
        None => text(&f["what"]),
    }
}

/// The newest camera frame (served by klipcal itself, `/api/backlash/snapshot.jpg`) with the
/// nozzle marked where the detector found it, and every cycle's approach positions. Pixel
/// centres are at integers in the detector's frame; the SVG's pixel i spans [i, i + 1], so a
/// mark is drawn at the centre + ½.
fn snapshot_figure(h: &mut String, s: &Value) {
    let f = &s["snapshot"];
    let (w, hh) = (
        f["width"].as_u64().unwrap_or(640),
        f["height"].as_u64().unwrap_or(480),
    );
    let seq = text(&f["seq"]);
    let click = f["click"] == Value::Bool(true);
    let hint = match (f["hint_px"][0].as_f64(), f["hint_px"][1].as_f64()) {
        (Some(x), Some(y)) => format!(
            " data-hint=\"{x:.3},{y:.3}\" data-zoom=\"{}\"",
            f["zoom"].as_f64().unwrap_or(4.0)
        ),
        _ => String::new(),
    };
    if click {
        let _ = write!(
            h,
            "<p class=\"msg ok\" id=\"clickhelp\"><b>Click the nozzle's tip</b> in the picture \
             below{}. <button class=\"quiet\" id=\"wholepic\">Whole picture</button></p>",
            if hint.is_empty() {
                ": a first click zooms in there, a second one marks the tip"
            } else {
                " (zoomed in where you clicked last)"
            }
        );
    }
    let _ = write!(
        h,
        "<figure id=\"snapshot\" data-seq=\"{seq}\" data-click=\"{}\"{hint}><div class=\"snap\">\
         <div class=\"stage\"><img id=\"snapimg\" src=\"/api/backlash/snapshot.jpg?seq={seq}\" \
         width=\"{w}\" height=\"{hh}\" alt=\"the nozzle camera's newest frame\">\
         <svg id=\"snapmarks\" viewBox=\"0 0 {w} {hh}\" preserveAspectRatio=\"none\" aria-hidden=\"true\">",
        u8::from(click)
    );
    let at = |p: &Value| {
        p[0].as_f64()
            .zip(p[1].as_f64())
            .map(|(x, y)| (x + 0.5, y + 0.5))
    };
    for rep in s["camera"].as_object().into_iter().flat_map(|o| o.values()) {
        for c in rep["cycles"].as_array().into_iter().flatten() {
            for (k, class) in [("plus_px", "plus"), ("minus_px", "minus")] {
                if let Some((x, y)) = at(&c[k]) {
                    let _ = write!(
                        h,
                        "<circle class=\"approach {class}\" cx=\"{x:.3}\" cy=\"{y:.3}\" r=\"1.5\"/>"
                    );
                }
            }
        }
    }
    // Waiting for a click, the detector's finding is not shown: the person judges the tip.
    let (found, (x, y)) = match at(&f["centre_px"]).filter(|_| !click) {
        Some(p) => ("", p),
        None => (" style=\"display:none\"", (0.0, 0.0)),
    };
    let r = f["radius_px"].as_f64().unwrap_or(20.0).max(4.0);
    let _ = write!(
        h,
        "<g id=\"found\" transform=\"translate({x:.3} {y:.3})\"{found}><circle r=\"{r:.1}\"/>\
         <line x1=\"-{r:.1}\" x2=\"{r:.1}\" y1=\"0\" y2=\"0\"/><line y1=\"-{r:.1}\" y2=\"{r:.1}\" x1=\"0\" x2=\"0\"/></g>\
         <g id=\"clicked\" style=\"display:none\"><circle r=\"3\"/></g></svg></div></div>\
         <figcaption id=\"snapcap\">{}</figcaption><small>{}blue dots: each cycle's nozzle \
         approached from below (moving +); orange: from above (moving −)</small></figure>",
        snapshot_caption(f),
        if found.is_empty() {
            "red cross: the nozzle as the detector found it; "
        } else {
            ""
        }
    );
}

/// One axis read through the camera: each cycle's approach positions and backlash, then the
/// median and spread the result gives.
fn camera_cycles(h: &mut String, key: &str, rep: &Value, result: &Value) {
    let scale = &rep["scale"];
    let _ = write!(
        h,
        "<div class=\"scroll camera\" data-key=\"{}\"><p><b>{}</b> from webcam '{}': \
         {} px/mm, rotation {}°, {} frames ({} refused and taken again)</p>\
         <table><tr><th>cycle</th><th>from below mm</th><th>from above mm</th><th>backlash mm</th></tr>",
        esc(key),
        esc(&key.to_uppercase()),
        text(&rep["webcam"]["name"]),
        scale["x"]["scale_px_per_mm"]
            .as_f64()
            .map(|v| format!("{v:.1}"))
            .unwrap_or_default(),
        scale["rotation_deg"]
            .as_f64()
            .map(|v| format!("{v:.1}"))
            .unwrap_or_default(),
        text(&rep["frames"]),
        text(&rep["refused_frames"])
    );
    let outliers: Vec<u64> = result["outliers"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(Value::as_u64)
        .collect();
    let f4 = |v: &Value| v.as_f64().map(|x| format!("{x:.4}")).unwrap_or_default();
    for (i, c) in rep["cycles"].as_array().into_iter().flatten().enumerate() {
        let _ = write!(
            h,
            "<tr class=\"cycle\"><td>{}{}</td><td>{}</td><td>{}</td><td class=\"b\">{}</td></tr>",
            i + 1,
            if outliers.contains(&(i as u64 + 1)) {
                " (outlier, left out)"
            } else {
                ""
            },
            f4(&c["plus_mm"]),
            f4(&c["minus_mm"]),
            f4(&c["backlash_mm"])
        );
    }
    if result.is_object() {
        let _ = write!(
            h,
            "<tr class=\"median\"><th colspan=\"3\">median ± uncertainty</th><td>{} ± {}</td></tr>\
             <tr class=\"spread\"><th colspan=\"3\">spread (largest − smallest kept)</th><td>{}</td></tr>",
            f4(&result["backlash_mm"]),
            f4(&result["uncertainty_mm"]),
            f4(&result["spread_mm"])
        );
    }
    h.push_str("</table></div>");
}

fn readings_form(h: &mut String, s: &Value, diagram_svg: Option<&str>) {
    let per_pair = s["readings_per_pair"].as_u64().unwrap_or(5) as usize;
    let on = if s["bed_temp_c"].as_f64().unwrap_or(0.0) > 0.0 {
        "with the part still on the hot bed"
    } else {
        "with the part still on the bed"
    };
    let _ = write!(
        h,
        "<section id=\"readings\"><h2>Readings</h2><p>Measure each pair {on}: {per_pair} readings with \
         calipers from outer face to outer face, just below the top chamfer. One reading per \
         field, as the caliper shows it (10.02 or 10,02); each pair is saved whole or not at \
         all.</p>"
    );
    if let Some(svg) = diagram_svg {
        // The diagram is the generator's own SVG (ids from the layout, no user text).
        let _ = write!(h, "<div class=\"diagram\">{svg}</div>");
    }
    let empty = serde_json::Map::new();
    let readings = s["readings"].as_object().unwrap_or(&empty);
    for p in s["pairs"].as_array().into_iter().flatten() {
        let id = p["id"].as_str().unwrap_or("");
        let have: Vec<f64> = readings
            .get(id)
            .and_then(Value::as_array)
            .map(|a| a.iter().filter_map(Value::as_f64).collect())
            .unwrap_or_default();
        let nominal = p["nominal_mm"].as_f64().unwrap_or(0.0);
        let _ = write!(
            h,
            "<fieldset class=\"pair\" data-pair=\"{}\"><legend>{}: pylon {} → pylon {}, nominal {} mm \
             <span class=\"saved\">({} of {per_pair} saved{})</span></legend>",
            esc(id),
            esc(id),
            text(&p["from"]),
            text(&p["to"]),
            mm(nominal),
            have.len(),
            match have.len().cmp(&per_pair) {
                std::cmp::Ordering::Less => "",
                std::cmp::Ordering::Equal => " ✓",
                std::cmp::Ordering::Greater => ": more than asked; Clear to enter the pair again",
            }
        );
        if !have.is_empty() {
            let list: Vec<String> = have.iter().map(|v| mm(*v)).collect();
            let _ = write!(
                h,
                "<p class=\"saved\">saved: {} <button class=\"clear quiet\">Clear</button></p>",
                esc(&list.join(", "))
            );
        }
        let open = per_pair.saturating_sub(have.len());
        if open > 0 {
            h.push_str("<div class=\"fields\">");
            for k in 0..open {
                let _ = write!(
                    h,
                    "<label class=\"field\"><input class=\"reading\" inputmode=\"decimal\" \
                     autocomplete=\"off\" aria-label=\"{} reading {}\" placeholder=\"{}\">\
                     <span class=\"err\"></span></label>",
                    esc(id),
                    have.len() + k + 1,
                    mm(nominal)
                );
            }
            h.push_str("</div><p class=\"row\"><button class=\"save\">Save ");
            h.push_str(&esc(id));
            h.push_str("</button></p>");
        }
        h.push_str("<p class=\"msg\"></p></fieldset>");
    }
    let missing = s["missing"].as_array().map_or(0, Vec::len);
    if state_is(s, "measuring") {
        let _ = write!(
            h,
            "<p class=\"row\"><button data-op=\"ab/solve\" data-out=\"solvemsg\"{}>Solve</button>\
             <span id=\"solvemsg\" class=\"msg\">{}</span></p>",
            if missing > 0 { " disabled" } else { "" },
            if missing > 0 {
                "enter every pair's readings to solve"
            } else {
                "all pairs measured"
            }
        );
    }
    h.push_str("</section>");
}

fn state_is(s: &Value, name: &str) -> bool {
    s["state"].as_str() == Some(name)
}

fn solution(h: &mut String, s: &Value) {
    let Some(r) = s["rounds"].as_array().and_then(|r| r.last()) else {
        return;
    };
    h.push_str("<section id=\"solution\"><h2>Solution</h2><div class=\"scroll\"><table><tr><th>stepper</th><th>rotation_<wbr>distance now</th><th>new</th><th>scale ± uncertainty</th></tr>");
    for (k, name) in ["stepper_x", "stepper_y"].iter().enumerate() {
        let f = |key: &str| r[key][k].as_f64();
        let _ = write!(
            h,
            "<tr><td>{name}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            f("rotation_distance")
                .map(crate::calib::entry::fmt_rd)
                .unwrap_or_default(),
            f("rotation_distance_new")
                .map(crate::calib::entry::fmt_rd)
                .unwrap_or_default(),
            match (f("scale"), f("uncertainty")) {
                (Some(sc), Some(u)) => format!("{sc:.5} ± {u:.5}"),
                _ => String::new(),
            }
        );
    }
    let _ = write!(
        h,
        "</table></div><p>{}</p><form class=\"row\"><label><input type=\"checkbox\" name=\"force\" style=\"width:auto\"> \
         apply even beyond the change limit (FORCE)</label><button data-op=\"ab/apply\" data-out=\"applymsg\" \
         data-confirm=\"Write the new rotation distances and restart Klipper?\">Apply</button></form>\
         <p id=\"applymsg\" class=\"msg\"></p></section>",
        if r["converged"] == Value::Bool(true) {
            "converged: within the error budget"
        } else {
            "not converged yet: apply, then print another round"
        }
    );
}

fn rounds_table(h: &mut String, s: &Value) {
    let Some(rounds) = s["rounds"].as_array().filter(|r| !r.is_empty()) else {
        return;
    };
    h.push_str("<section id=\"rounds\"><h2>Rounds</h2><div class=\"scroll\"><table><tr><th>round</th><th>job</th><th>error µm/100&nbsp;mm</th><th>converged</th><th>applied</th></tr>");
    let mut solved = false;
    for r in rounds {
        solved |= !r["scale"].is_null();
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            text(&r["n"]),
            text(&r["file"]),
            r["error_um_per_100mm"]
                .as_f64()
                .map(|v| format!("{v:.1}"))
                .unwrap_or_default(),
            match r["converged"].as_bool() {
                Some(true) => "yes",
                Some(false) => "no",
                None => "",
            },
            if r["applied"].is_null() { "" } else { "yes" }
        );
    }
    h.push_str("</table></div>");
    if solved {
        let _ = write!(
            h,
            "<img class=\"plot\" alt=\"convergence\" src=\"/api/sessions/{}/convergence.svg\">",
            text(&s["id"])
        );
    }
    h.push_str("</section>");
}

fn last_results(h: &mut String, last: &Value, shown: &Value) {
    let Some(map) = last.as_object().filter(|m| !m.is_empty()) else {
        return;
    };
    let rows: Vec<(&String, &Value)> = map.iter().filter(|(_, s)| s["id"] != shown["id"]).collect();
    if rows.is_empty() {
        return;
    }
    h.push_str("<section><h2>Last sessions</h2><table>");
    for (kind, s) in rows {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>session {}</td><td>{}</td><td>{}</td></tr>",
            esc(kind),
            text(&s["id"]),
            text(&s["state"]),
            text(&s["progress"])
        );
    }
    h.push_str("</table></section>");
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// Every key anywhere in `v`.
    fn keys_of(v: &Value, out: &mut std::collections::BTreeSet<String>) {
        match v {
            Value::Object(o) => {
                for (k, x) in o {
                    out.insert(k.clone());
                    keys_of(x, out);
                }
            }
            Value::Array(a) => a.iter().for_each(|x| keys_of(x, out)),
            _ => {}
        }
    }

    /// A camera report with every part filled in.
    fn camera_report() -> crate::jobs::backlash::camera::CameraReport {
        use crate::calib::camera_scale::{fit_axis, CameraScale, Sighting};
        let sight = |dir: [f64; 2]| -> Vec<Sighting> {
            [-0.5, 0.0, 0.5]
                .map(|t| Sighting {
                    commanded_mm: t,
                    centre_px: [320.0 + 80.0 * t * dir[0], 240.0 + 80.0 * t * dir[1]],
                    uncertainty_px: 0.02,
                })
                .to_vec()
        };
        let scale = CameraScale::from_axes(
            fit_axis("x", &sight([1.0, 0.0])).unwrap(),
            fit_axis("y", &sight([0.0, 1.0])).unwrap(),
        )
        .unwrap();
        crate::jobs::backlash::camera::CameraReport {
            webcam: crate::jobs::backlash::camera::Webcam {
                name: "nozzle".into(),
                snapshot_url: String::new(),
            },
            scale: Some(scale),
            reference_px: Some([320.0, 240.0]),
            cycles: vec![crate::jobs::backlash::camera::CameraCycle {
                plus_px: [320.0, 240.0],
                minus_px: [326.0, 240.0],
                plus_mm: 0.0,
                minus_mm: 0.08,
                backlash_mm: 0.08,
            }],
            detection_sd_px: 0.02,
            axis_px_per_mm: 80.0,
            frames: 12,
            refused_frames: 0,
            last_px: None,
            clicks: 0,
        }
    }

    /// A status of each kind, built from the typed structs the agent serializes, with every
    /// nested part filled in.
    fn typed_status_keys() -> std::collections::BTreeSet<String> {
        use crate::agent::{Connection, DaemonInfo, PageInfo, StatusAnswer};
        use crate::jobs::ab::{AbRoundStatus, AbStatus};
        use crate::jobs::backlash::BacklashStatus;
        use crate::jobs::core::envelope::StatusHead;
        use crate::jobs::core::status::{SessionStatus, SessionsStatus};
        use crate::jobs::mesh::{FollowReading, FollowStatus, MeshStatus, ResultDoc};
        let head = StatusHead {
            id: 1,
            state: "measuring".into(),
            progress: String::new(),
            reason: None,
            notes: vec![],
        };
        let ab = AbStatus {
            pairs: Some(vec![crate::layout::Pair {
                id: "A-D1".into(),
                group: "A".into(),
                from: "A1".into(),
                to: "A2".into(),
                direction_deg: 0.0,
                nominal_mm: 10.0,
            }]),
            rounds: vec![AbRoundStatus::default()],
            ..AbStatus::default()
        };
        let mesh = MeshStatus {
            result: Some(ResultDoc {
                model: "linear".into(),
                models: vec![],
                vgb: None,
                range_c: (25.0, 40.0),
                profiles_c: vec![],
                max_quantisation_um: 0.0,
                backup: None,
                replaced: vec![],
                directions: String::new(),
                cooling: None,
            }),
            // Both the reading and the reason, so that every key of the follower is listed.
            follow: FollowStatus {
                following: true,
                stopped: Some(String::new()),
                reading: Some(FollowReading {
                    frame_c: 0.0,
                    trend: crate::calib::mesh::Phase::Heating,
                    loaded: Some(String::new()),
                    offset_mm: [0.0; 2],
                    residual_um: Some(0.0),
                }),
            },
            ..MeshStatus::default()
        };
        let cycles = vec![0.1, 0.11, 0.1, 0.12, 0.1]
            .into_iter()
            .map(|b| crate::calib::backlash::Cycle {
                x1_mm: b,
                x2_mm: 0.0,
                fine_mm: None,
            })
            .collect::<Vec<_>>();
        let result = crate::calib::backlash::analyse(
            "x",
            &cycles,
            None,
            &crate::config::BacklashConfig::default().params(),
        )
        .unwrap();
        let backlash = BacklashStatus {
            point: [0.0; 3],
            branch: crate::klipper::backlash::detect(&json!({}), &Default::default()).unwrap(),
            axis: None,
            cycle: None,
            cycles: [("x".to_string(), cycles)].into(),
            corexy_answer: None,
            results: [("x".to_string(), result)].into(),
            active_mm: Default::default(),
            camera: [("x".to_string(), camera_report())].into(),
            snapshot: Some(crate::jobs::backlash::snapshot::SnapshotInfo {
                seq: 1,
                width: 640,
                height: 480,
                what: String::new(),
                centre_px: Some([1.0, 2.0]),
                radius_px: Some(20.0),
                uncertainty_px: Some(0.03),
                refused: Some(String::new()),
                click: false,
                hint_px: Some([1.0, 2.0]),
                zoom: Some(4.0),
            }),
        };
        let mut last = std::collections::BTreeMap::new();
        last.insert(
            "ab".into(),
            SessionStatus::new("ab", head.clone(), &ab).unwrap(),
        );
        last.insert(
            "mesh".into(),
            SessionStatus::new("mesh", head.clone(), &mesh).unwrap(),
        );
        last.insert(
            "backlash".into(),
            SessionStatus::new("backlash", head.clone(), &backlash).unwrap(),
        );
        let answer = StatusAnswer {
            page: Some(PageInfo {
                address: Some(String::new()),
                off: Some(String::new()),
            }),
            daemon: DaemonInfo {
                name: "klipcal",
                version: "0",
            },
            connection: Connection {
                moonraker: "unreachable",
                klippy_state: Some("ready".into()),
                last_error: Some(None),
                message: Some(String::new()),
            },
            printer: None,
            sessions: SessionsStatus {
                session: last.get("ab").cloned(),
                last,
            },
        };
        let mut keys = std::collections::BTreeSet::new();
        keys_of(&serde_json::to_value(answer).unwrap(), &mut keys);
        keys
    }

    #[test]
    fn every_status_key_the_page_reads_is_a_field_of_the_typed_status() {
        let source = include_str!("mod.rs");
        let source = &source[..source.find("#[cfg(test)]").unwrap()];
        let mut read = std::collections::BTreeSet::new();
        // The Rust side: `x["key"]`, `x["a"]["key"]` (not an array literal `["a", "b"]`).
        for (at, _) in source.match_indices("[\"") {
            let before = source[..at].chars().next_back().unwrap_or(' ');
            if !(before.is_ascii_alphanumeric() || before == '_' || before == ']') {
                continue;
            }
            let part = &source[at + 2..];
            if let Some(end) = part.find("\"]") {
                read.insert(part[..end].to_string());
            }
        }
        // The script's poll: `s.key` (the session), `j.key` and `j.connection.key`.
        let poll = &SCRIPT[SCRIPT.find("async function poll").unwrap()..];
        let poll = &poll[..poll.find("setInterval(poll").unwrap()];
        for prefix in ["s.", "j.", "j.connection."] {
            for part in poll.split(prefix).skip(1) {
                let key: String = part
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect();
                if !key.is_empty() && !["textContent", "style", "json"].contains(&key.as_str()) {
                    read.insert(key);
                }
            }
        }
        assert!(
            read.len() > 40,
            "the page reads {} keys: {read:?}",
            read.len()
        );
        // `ok`, `error` and `message` are the answer's wrapping (`http::answer`), not the
        // status.
        let wrapping = ["ok", "error", "message"];
        let have = typed_status_keys();
        for follower in ["following", "stopped", "loaded", "residual_um", "frame_c"] {
            assert!(read.contains(follower), "the page reads {follower}");
        }
        let missing: Vec<&String> = read
            .iter()
            .filter(|k| !have.contains(*k))
            .filter(|k| !wrapping.contains(&k.as_str()))
            .collect();
        assert!(
            missing.is_empty(),
            "the page reads keys no typed status has: {missing:?}"
        );
    }

    fn measuring() -> Value {
        json!({"ok": true, "daemon": {"version": "0.1.0"}, "connection": {"klippy_state": "ready"},
            "session": {"kind": "ab", "id": 4, "state": "measuring", "round": 1,
                "progress": "waiting for caliper readings <now>", "readings_per_pair": 5, "bed_temp_c": 0.0,
                "pairs": [{"id": "A-D1", "from": "A1", "to": "A2", "nominal_mm": 10.0},
                          {"id": "A-D2", "from": "A1", "to": "A3", "nominal_mm": 150.0}],
                "readings": {"A-D1": [10.02, 10.03]}, "missing": ["A-D1: 3 more", "A-D2: 5 more"],
                "rounds": [{"n": 1, "file": "klipcal/ab-s4-r1.gcode", "scale": null}], "notes": []},
            "last": {}})
    }

    #[test]
    fn the_readings_form_has_a_field_per_missing_reading_and_shows_saved_ones() {
        let page = render(
            &measuring(),
            Some("<svg><g class=\"pair\" data-pair=\"A-D1\"></g></svg>"),
        );
        assert_eq!(page.matches("class=\"reading\"").count(), 3 + 5, "{page}");
        assert!(page.contains("saved: 10.02, 10.03"));
        assert!(page.contains("(2 of 5 saved)"));
        assert!(page.contains("A-D2: pylon A1 → pylon A3, nominal 150 mm"));
        assert!(
            page.contains("data-pair=\"A-D1\"></g>"),
            "the diagram is inline"
        );
        // BED=0: no "hot bed".
        assert!(page.contains("with the part still on the bed") && !page.contains("hot bed"));
        assert!(page.contains("data-op=\"ab/solve\"") && page.contains(" disabled>Solve"));
    }

    #[test]
    fn a_mesh_session_shows_its_meshes_models_and_follow_state() {
        let st = json!({"ok": true, "session": {"kind": "mesh", "id": 7, "state": "done", "progress": "written",
            "frame_c": [28.25, 28.9], "follow": {"following": true, "frame_c": 29.1, "loaded": "klipcal_29.05", "residual_um": 1.2},
            "result": {"model": "linear", "models": [["linear", 4.0, 1.5, 2.0]], "vgb": [9.0, 3.0, 4.0],
                       "range_c": [28.2, 29.4], "profiles_c": [28.3, 28.9, 29.3], "max_quantisation_um": 4.2}},
            "last": {}});
        let page = render(&st, None);
        assert!(
            page.contains("2 mesh(es) at frame 28.25, 28.90 °C"),
            "{page}"
        );
        assert!(page.contains("3 profiles klipcal_* over 28.20–29.40 °C"));
        assert!(page.contains("<td>VGB two-mesh</td><td>9.0</td>"));
        assert!(page.contains("profile klipcal_29.05, residual 1.2 µm"));
        assert!(page.contains("data-op=\"mesh/follow\""));
    }

    #[test]
    fn a_backlash_session_shows_its_results_and_apply() {
        let st = json!({"ok": true, "session": {"kind": "backlash", "id": 9, "state": "measured",
            "progress": "x measured", "axis": null,
            "results": {"x": {"backlash_mm": 0.0812, "uncertainty_mm": 0.0021, "spread_mm": 0.004,
                              "cycles": 5, "compensate": true, "smooth_time_s": 0.005}}},
            "last": {}});
        let page = render(&st, None);
        assert!(
            page.contains("<td>x</td><td>0.081</td><td>0.002</td>"),
            "{page}"
        );
        assert!(page.contains("data-op=\"backlash/apply\""));
    }

    #[test]
    fn a_camera_frame_is_shown_with_its_mark_or_as_the_snapshot_to_click_in() {
        let mut st = json!({"ok": true, "session": {"kind": "backlash", "id": 9, "state": "measuring",
            "progress": "camera", "axis": null,
            "snapshot": {"seq": 12, "width": 640, "height": 480, "what": "X cycle 1/5 <b>",
                         "centre_px": [300.25, 200.5], "radius_px": 28.0, "uncertainty_px": 0.05,
                         "refused": null, "click": false, "hint_px": null},
            "camera": {"x": {"webcam": {"name": "nozzle"}, "scale": {"x": {"scale_px_per_mm": 80.0},
                "rotation_deg": 12.0}, "frames": 9, "refused_frames": 1,
                "cycles": [{"plus_px": [300.0, 200.0], "minus_px": [306.0, 200.0],
                            "plus_mm": 0.0012, "minus_mm": 0.0814, "backlash_mm": 0.0802}]}}},
            "last": {}});
        let page = render(&st, None);
        assert!(
            page.contains("src=\"/api/backlash/snapshot.jpg?seq=12\""),
            "{page}"
        );
        // The mark at the detector's centre, + ½ for the SVG's pixel edges.
        assert!(page.contains("<g id=\"found\" transform=\"translate(300.750 201.000)\">"));
        assert!(page.contains("X cycle 1/5 &lt;b&gt;: nozzle at (300.25, 200.50) px ± 0.05 px"));
        assert!(page.contains("<td>0.0012</td><td>0.0814</td><td class=\"b\">0.0802</td>"));
        assert_eq!(page.matches("class=\"approach ").count(), 2);
        assert!(page.contains("data-sig=\"9|measuring||{}|1\""), "{page}");
        // Waiting for a click: no detector's mark, the help and the zoom's hint.
        st["session"]["snapshot"]["click"] = json!(true);
        st["session"]["snapshot"]["hint_px"] = json!([310.0, 205.5]);
        st["session"]["snapshot"]["zoom"] = json!(8.0);
        let page = render(&st, None);
        assert!(page.contains("data-click=\"1\" data-hint=\"310.000,205.500\" data-zoom=\"8\""));
        assert!(page.contains("id=\"clickhelp\"") && page.contains("Click the nozzle's tip"));
        assert!(page.contains(
            "<g id=\"found\" transform=\"translate(0.000 0.000)\" style=\"display:none\">"
        ));
        // A refused frame says why.
        st["session"]["snapshot"]["click"] = json!(false);
        st["session"]["snapshot"]["centre_px"] = Value::Null;
        st["session"]["snapshot"]["refused"] = json!("two candidates");
        assert!(render(&st, None).contains("X cycle 1/5 &lt;b&gt;: no reading, two candidates"));
    }

    #[test]
    fn document_text_is_escaped() {
        let page = render(&measuring(), None);
        assert!(page.contains("waiting for caliper readings &lt;now&gt;"));
        assert!(!page.contains("<now>"));
    }

    #[test]
    fn no_session_offers_the_start_form_and_an_error_is_shown() {
        let page = render(&json!({"ok": true, "session": null, "last": {}}), None);
        assert!(page.contains("data-op=\"ab/start\""));
        let page = render(
            &json!({"ok": false, "error": {"message": "no database"}}),
            None,
        );
        assert!(page.contains("Status unavailable") && page.contains("no database"));
    }

    #[test]
    fn every_operation_with_an_http_path_has_a_form_with_a_field_per_argument() {
        let page = render(&json!({"session": null, "last": {}}), None);
        for op in crate::jobs::registry::all_ops() {
            let Some(path) = op.http else { continue };
            assert!(
                page.contains(&format!("data-op=\"{path}\" data-out=\"op-")),
                "no form for {path}"
            );
            let form = page
                .split(&format!("data-path=\"{path}\""))
                .nth(1)
                .and_then(|f| f.split("</form>").next())
                .unwrap();
            for a in op.args {
                assert!(
                    form.contains(&format!("name=\"{}\"", a.name)),
                    "{path} has no field {}",
                    a.name
                );
            }
        }
        // The soak's answer, which the page once lacked (issue 24).
        assert!(page.contains("data-op=\"ab/soak_choice\""));
    }

    #[test]
    fn a_solved_session_shows_the_values_and_the_apply_button() {
        let mut st = measuring();
        st["session"]["state"] = json!("solved");
        st["session"]["missing"] = json!([]);
        st["session"]["rounds"] = json!([{"n": 1, "file": "f", "rotation_distance": [40.0, 40.0],
            "rotation_distance_new": [40.08, 39.96], "scale": [1.002, 0.999], "uncertainty": [0.0001, 0.0001],
            "error_um_per_100mm": 200.0, "converged": false, "applied": null}]);
        let page = render(&st, None);
        assert!(
            // One precision everywhere (issue 9 item 22): as the console and the config say it.
            page.contains("<td>40</td><td>40.08</td>")
                && !page.contains("40.000000")
                && page.contains("1.00200 ± 0.00010"),
            "{page}"
        );
        assert!(page.contains("data-op=\"ab/apply\""));
        assert!(page.contains("/api/sessions/4/convergence.svg"));
    }
}
