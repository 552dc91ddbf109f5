// Starts `softc lsp` for .soft files. Highlighting works without it (the grammar is static).
'use strict';
const vscode = require('vscode');

let client;

function activate(context) {
  const command = vscode.workspace.getConfiguration('softc').get('path', 'softc');
  if (!command) return;
  let lc;
  try {
    lc = require('vscode-languageclient/node');
  } catch (e) {
    vscode.window.showWarningMessage('softc: run `npm install` in the extension folder to enable the language server');
    return;
  }
  client = new lc.LanguageClient(
    'softc',
    'softc language server',
    { command, args: ['lsp'], transport: lc.TransportKind.stdio },
    { documentSelector: [{ language: 'soft' }] },
  );
  client.start().catch((e) =>
    vscode.window.showWarningMessage(`softc: cannot start \`${command} lsp\`: ${e.message}`),
  );
  context.subscriptions.push({ dispose: () => client && client.stop() });
}

function deactivate() {
  return client ? client.stop() : undefined;
}

module.exports = { activate, deactivate };
