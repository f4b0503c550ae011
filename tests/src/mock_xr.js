// A scripted WebXR device for the browser tests: `navigator.xr` offers 'immersive-vr' and
// 'immersive-ar' (the mode asked is kept in `window.__xrMode`); a
// session hands out frames with two views (eyes 64 mm apart at 1.6 m height, 3 m from the
// origin, looking down -z) and a 640x240 layer framebuffer (320x240 per eye). Every WebGL
// viewport the page sets is recorded in `window.__xrViewports`; the live session is
// `window.__xrSession` (end it with `window.__xrSession.end()`).
(() => {
  const near = 0.1, far = 100, f = 1 / Math.tan(Math.PI / 6), aspect = 320 / 240;
  const projection = new Float32Array([
    f / aspect, 0, 0, 0,
    0, f, 0, 0,
    0, 0, (far + near) / (near - far), -1,
    0, 0, (2 * far * near) / (near - far), 0,
  ]);
  const view = (eye, x) => ({
    eye,
    // The view (world-to-eye) matrix, column-major: a translation by -(x, 1.6, 3).
    transform: { inverse: { matrix: new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, -x, -1.6, -3, 1]) } },
    projectionMatrix: projection,
  });
  const frame = { getViewerPose: () => ({ views: [view('left', -0.032), view('right', 0.032)] }) };

  class MockLayer {
    constructor() {
      this.framebuffer = null;
      this.framebufferWidth = 640;
      this.framebufferHeight = 240;
    }
    getViewport(v) {
      return { x: v.eye === 'left' ? 0 : 320, y: 0, width: 320, height: 240 };
    }
  }

  class MockSession extends EventTarget {
    constructor() {
      super();
      this.renderState = {};
      this.ended = false;
    }
    updateRenderState(state) { Object.assign(this.renderState, state); }
    requestReferenceSpace() { return Promise.resolve({}); }
    requestAnimationFrame(callback) {
      if (!this.ended) setTimeout(() => { if (!this.ended) callback(performance.now(), frame); }, 16);
      return 1;
    }
    end() {
      this.ended = true;
      this.dispatchEvent(new Event('end'));
      return Promise.resolve();
    }
  }

  window.__xrViewports = [];
  const viewport = WebGLRenderingContext.prototype.viewport;
  WebGLRenderingContext.prototype.viewport = function (x, y, width, height) {
    window.__xrViewports.push([x, y, width, height]);
    return viewport.call(this, x, y, width, height);
  };
  WebGLRenderingContext.prototype.makeXRCompatible = () => Promise.resolve();
  window.XRWebGLLayer = MockLayer;
  Object.defineProperty(navigator, 'xr', {
    configurable: true,
    value: {
      isSessionSupported: (mode) => Promise.resolve(mode === 'immersive-vr' || mode === 'immersive-ar'),
      requestSession: (mode) => {
        window.__xrMode = mode;
        return Promise.resolve((window.__xrSession = new MockSession()));
      },
    },
  });
})();
