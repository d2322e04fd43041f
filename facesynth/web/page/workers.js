// One worker (worker.js) and its messages, for the live page and the studio alike: the messages
// the page handles by type go to `on[type]`; a call's answer (by id) settles that call's promise
// in `pending`; any other error goes to `onError`. `w.ready` settles when the worker has started.
export function spawnWorker({ base, tracker, pending, on, onError, onStartFailed }) {
  const w = new Worker('worker.js', { type: 'module' });
  w.ready = new Promise((resolve, reject) => { w.started = resolve; w.failed = reject; });
  w.onmessage = (ev) => {
    const m = ev.data, p = pending.get(m.id), handle = on[m.type];
    if (m.type === 'ready') w.started();
    else if (handle) handle(m, w);
    else if (p) { pending.delete(m.id); if (m.type === 'error') p.reject(new Error(m.message)); else p.resolve(m); }
    else if (m.type === 'error') { onError(m, w); w.failed(new Error(m.message)); }
  };
  w.onerror = (e) => w.failed(onStartFailed(e));  // the worker's script itself failed
  w.postMessage({ type: 'init', base, tracker });
  return w;
}
