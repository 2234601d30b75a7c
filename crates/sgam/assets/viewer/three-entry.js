// Entry of the vendored three.js bundle (three.bundle.min.js): everything the viewer page uses,
// exposed as one global. Rebuild with the command in README.md; the page's own code is viewer.js.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

window.SGAM_THREE = { THREE, OrbitControls, GLTFLoader };
