// Loads the viewer, or says clearly why it cannot: the JavaScript packages (three.js, cannon-es)
// are served from the repository's node_modules, which `npm ci` (scripts/setup.sh) installs.

function showMessage(html) {
  const m = document.getElementById('message');
  m.innerHTML = html;
  m.hidden = false;
}

async function boot() {
  let ok = false;
  try {
    ok = (await fetch('/vendor/three/package.json', { method: 'HEAD', cache: 'no-store' })).ok;
  } catch {
    ok = false;
  }
  if (!ok) {
    window.dbbBootError = 'three.js is not installed';
    showMessage('<b>The viewer\'s JavaScript packages are missing.</b><br>dbb-serve serves three.js and ' +
      'cannon-es from the repository\'s <code>node_modules</code>: run <code>npm ci</code> in the ' +
      'repository (<code>scripts/setup.sh</code> does it), or set <code>DBB_NODE_MODULES</code> to a ' +
      'folder that has them, and restart dbb-serve. The stream itself works without them ' +
      '(<code>/hello.json</code>, <code>/ws</code>).');
    return;
  }
  try {
    await import('./main.js');
  } catch (e) {
    window.dbbBootError = String(e);
    showMessage(`<b>The viewer failed to start.</b><br>${String(e).replace(/</g, '&lt;')}`);
    throw e;
  }
}

boot();
