// Tokenize every example script (examples/*.soft) and every grammar fixture with the TextMate
// grammar and check the highlighting against the compiler's own word lists:
//   * no token is scoped `invalid.*`;
//   * every reserved keyword (read from compiler/src/front/soft.pest) outside comments and
//     strings gets a keyword-like scope (or is an argument/setting name, which may be a keyword);
//   * every unit written after a number (names read from compiler/src/sema/units.rs) is scoped
//     `keyword.other.unit.soft`;
//   * every built-in function call (names from compiler/src/sema/builtins.rs) is scoped
//     `support.function.*` (or is shadowed by a declaration of the script);
//   * every number is scoped `constant.numeric.*`.
// Exit status 1 on any failure. Run from lang-spec/editors (npm test does).

'use strict';
const fs = require('fs');
const path = require('path');
const vsctm = require('vscode-textmate');
const oniguruma = require('vscode-oniguruma');

const root = path.resolve(__dirname, '..', '..', '..');
const grammarPath = path.join(__dirname, '..', 'vscode', 'syntaxes', 'soft.tmLanguage.json');

function read(rel) {
  return fs.readFileSync(path.join(root, rel), 'utf8');
}

// Word lists from the compiler sources.
const pest = read('compiler/src/front/soft.pest');
const kwBlock = pest.slice(pest.indexOf('keyword = @{'), pest.indexOf('~ !ident_char', pest.indexOf('keyword = @{')));
const KEYWORDS = [...kwBlock.matchAll(/"([a-z]+)"/g)].map((m) => m[1]);
const unitsRs = read('compiler/src/sema/units.rs');
const unitBlock = unitsRs.slice(unitsRs.indexOf('pub const UNIT_NAMES'));
const UNITS = [...unitBlock.slice(0, unitBlock.indexOf('];')).matchAll(/"([^"]+)"/g)].map((m) => m[1]);
const builtinsRs = read('compiler/src/sema/builtins.rs');
const fnBlock = builtinsRs.slice(builtinsRs.indexOf('pub const FUNCTIONS'));
const FUNCTIONS = [...fnBlock.slice(0, fnBlock.indexOf('];')).matchAll(/"([a-z_0-9]+)"/g)].map((m) => m[1]);
if (KEYWORDS.length !== 37 || UNITS.length < 30 || FUNCTIONS.length < 40) {
  console.error(`could not read the word lists: ${KEYWORDS.length} keywords, ${UNITS.length} units, ${FUNCTIONS.length} functions`);
  process.exit(1);
}

const wasm = fs.readFileSync(path.join(path.dirname(require.resolve('vscode-oniguruma')), 'onig.wasm')).buffer;
const onigLib = oniguruma.loadWASM(wasm).then(() => ({
  createOnigScanner: (p) => new oniguruma.OnigScanner(p),
  createOnigString: (s) => new oniguruma.OnigString(s),
}));
const registry = new vsctm.Registry({
  onigLib,
  loadGrammar: async (scope) =>
    scope === 'source.soft'
      ? vsctm.parseRawGrammar(fs.readFileSync(grammarPath, 'utf8'), grammarPath)
      : null,
});

function checkFile(grammar, file) {
  const text = fs.readFileSync(file, 'utf8');
  const declared = new Set([...text.matchAll(/\b(?:mesh|region|chamber|nodes|elements|obstacle|param|input|let|fn|controller|material)\s+([A-Za-z_]\w*)/g)].map((m) => m[1]));
  const errors = [];
  let state = vsctm.INITIAL;
  const lines = text.split('\n');
  let tokens = 0;
  lines.forEach((line, ln) => {
    const r = grammar.tokenizeLine(line, state);
    state = r.ruleStack;
    const toks = r.tokens.map((t) => ({ text: line.slice(t.startIndex, t.endIndex), scopes: t.scopes, start: t.startIndex, end: t.endIndex }));
    tokens += toks.length;
    const where = (t) => `${path.relative(root, file)}:${ln + 1}:${t.start + 1}`;
    const has = (t, prefix) => t.scopes.some((s) => s.startsWith(prefix));
    const inText = (t) => has(t, 'comment') || has(t, 'string');
    toks.forEach((t, i) => {
      if (t.scopes.some((s) => s.includes('invalid'))) {
        errors.push(`${where(t)}: \`${t.text}\` is scoped invalid (${t.scopes.join(' ')})`);
      }
      if (inText(t)) return;
      // Words inside one token (a unit token may be one word; others are single words).
      for (const m of t.text.matchAll(/[A-Za-z_][\w]*/g)) {
        const w = m[0];
        if (KEYWORDS.includes(w) && w === t.text.trim()) {
          const ok = ['storage.type', 'keyword', 'constant.language', 'variable.parameter', 'variable.other.property.setting'].some((p) => has(t, p));
          if (!ok) errors.push(`${where(t)}: keyword \`${w}\` scoped ${t.scopes.join(' ')}`);
        }
      }
      if (/^\d|^\.\d/.test(t.text.trim()) && !has(t, 'constant.numeric') && !has(t, 'meta.unit')) {
        errors.push(`${where(t)}: number \`${t.text}\` scoped ${t.scopes.join(' ')}`);
      }
      // A unit right after a number: `3 kPa`, `8 /s`, `1070 kg/m^3`.
      if (has(t, 'constant.numeric') && !has(t, 'meta.unit')) {
        const rest = line.slice(t.end);
        const m = rest.match(/^[ \t]*\/?([A-Za-zµμ][\wµμ]*)/);
        if (m && UNITS.includes(m[1])) {
          const at = t.end + m[0].length - m[1].length;
          const u = toks.find((x) => x.start <= at && at < x.end);
          if (!u || !has(u, 'keyword.other.unit')) {
            errors.push(`${where(t)}: unit \`${m[1]}\` after a number scoped ${u ? u.scopes.join(' ') : 'nothing'}`);
          }
        }
      }
      // Built-in calls.
      const w = t.text;
      if (FUNCTIONS.includes(w) && /^\s*\(/.test(line.slice(t.end)) && !declared.has(w) && !has(t, 'meta.unit')) {
        if (!has(t, 'support.function')) {
          errors.push(`${where(t)}: built-in call \`${w}\` scoped ${t.scopes.join(' ')}`);
        }
      }
    });
  });
  return { errors, tokens };
}

(async () => {
  const grammar = await registry.loadGrammar('source.soft');
  const files = [
    ...fs.readdirSync(path.join(root, 'examples')).filter((f) => f.endsWith('.soft')).map((f) => path.join(root, 'examples', f)),
    ...fs.readdirSync(__dirname).filter((f) => f.endsWith('.soft')).map((f) => path.join(__dirname, f)),
  ].sort();
  if (files.filter((f) => f.includes(`${path.sep}examples${path.sep}`)).length < 4) {
    console.error('no example scripts found');
    process.exit(1);
  }
  let failed = 0;
  for (const f of files) {
    const { errors, tokens } = checkFile(grammar, f);
    // The fixtures contain deliberate invalid tokens (asserted there): only examples must be clean.
    const relevant = f.includes(`${path.sep}examples${path.sep}`) ? errors : errors.filter((e) => !e.includes('scoped invalid'));
    if (relevant.length) {
      failed += 1;
      console.error(`✖ ${path.relative(root, f)}\n  ${relevant.join('\n  ')}`);
    } else {
      console.log(`✓ ${path.relative(root, f)} (${tokens} tokens)`);
    }
  }
  if (failed) process.exit(1);
})().catch((e) => {
  console.error(e);
  process.exit(1);
});
