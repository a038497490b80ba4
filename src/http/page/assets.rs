//! The page's inline style sheet and script (no build step, no external resources).

pub(super) const STYLE: &str = r#"
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
form.inline{display:inline}figure{margin:.4em 0}figcaption{font-size:.9em}
.saved{color:#495057;font-size:.9em}.scroll{overflow-x:auto}small{color:#495057}
#jog .jogs{display:grid;grid-template-columns:repeat(auto-fill,minmax(7.5em,1fr));gap:.4em}#jog form{display:contents}#jog button{padding:.7em .4em;min-height:2.8em}
#jog img{width:100%;max-height:45vh;object-fit:contain;background:#000;color:#dee2e6;display:block}
@media (max-width:600px){main{padding:.3em}section{padding:.6em .5em}td,th{padding:.2em .25em;font-size:.88em}}
"#;

pub(super) const SCRIPT: &str = r#"
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
    const now=[s.id,s.state,s.round,JSON.stringify(s.readings||{}),Object.values(s.camera||{}).reduce((n,c)=>n+(c.cycles||[]).length,0),(s.jog||[]).map(b=>b.press).join(','),s.cycle==null?'':s.cycle].join('|');
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
const live=$('#live');if(live){let busy=false;live.addEventListener('load',()=>{busy=false});live.addEventListener('error',()=>{busy=false});
  setInterval(()=>{if(!busy){busy=true;live.src='/api/backlash/live.jpg?t='+Date.now()}},1000)}
const soak=$('#soak');if(soak)setInterval(()=>{soak.src='/api/plots/soak.svg?t='+Date.now()},15000);
"#;
