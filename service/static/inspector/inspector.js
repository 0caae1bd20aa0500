// The grasp inspector: draws what the API returns for one session, nothing else.
//   GET /grasp?session_id=…   grasps (palm pose, joints, ε, volume, the hand's primitives placed
//                             by its kinematics), the camera pose and the support plane
//   GET /sessions/{id}/mesh?format=obj   the completion mesh
//   GET /sessions/{id}/observed          the latest view's observed points, the obstacles
// Everything is in the latest view's camera frame (OpenCV: x right, y down, z forward); the
// root group turns it into three.js's y-up convention.
import * as THREE from 'three';
import { OrbitControls } from './vendor/three/OrbitControls.js';
import { OBJLoader } from './vendor/three/OBJLoader.js';

const statusEl = document.getElementById('status');
const listEl = document.getElementById('grasps');

function fail(message) {
  statusEl.dataset.state = 'error';
  statusEl.textContent = String(message);
}
window.addEventListener('error', (e) => fail(e.message));
window.addEventListener('unhandledrejection', (e) => fail(e.reason));

const parts = location.pathname.split('/');
const sessionId = decodeURIComponent(parts[parts.length - 2]);
const query = new URLSearchParams(location.search);
const token = new URLSearchParams(location.hash.slice(1)).get('token');
const headers = token ? { Authorization: `Bearer ${token}` } : {};
document.getElementById('session').textContent = `session ${sessionId}`;

async function api(path) {
  const response = await fetch(path, { headers });
  if (!response.ok) throw new Error(`${path}: HTTP ${response.status} ${await response.text()}`);
  return response;
}

// /observed's points: base64 of float32 rows (format f32, the default) or [x, y, z] lists (json)
function xyz(field, format) {
  if (format !== 'f32') return new Float32Array(field.flat());
  const bytes = Uint8Array.from(atob(field), (c) => c.charCodeAt(0));
  return new Float32Array(bytes.buffer);
}

function matrix(rows) {
  const m = new THREE.Matrix4();
  m.set(...rows.flat());
  return m;
}

function place(object, rows) {
  object.matrixAutoUpdate = false;
  object.matrix.copy(matrix(rows));
  return object;
}

const HAND = { color: 0x555a66, roughness: 0.6, metalness: 0.2 };

function handGroup(grasp) {
  const group = new THREE.Group();
  for (const prim of grasp.hand) {
    let geometry;
    if (prim.kind === 'box') {
      geometry = new THREE.BoxGeometry(...prim.size);
    } else {
      const [radius, length] = prim.size;
      geometry = new THREE.CylinderGeometry(radius, radius, length, 24);
      geometry.rotateX(Math.PI / 2); // three.js cylinders run along y, ours along z
    }
    const material = new THREE.MeshStandardMaterial({ ...HAND, transparent: true });
    group.add(place(new THREE.Mesh(geometry, material), prim.pose));
    if (grasp.kind === 'table pinch' && prim.link === 'palm') {
      // a table pinch closes while the palm rises: its palm where closing starts, as an
      // outline, and the rise from there to where the hand is drawn (where closing ends)
      const start = prim.pose.map((row) => row.slice());
      for (let i = 0; i < 3; i += 1) {
        start[i][3] += grasp.palm_pose[i][3] - grasp.end_palm_pose[i][3];
      }
      const outline = new THREE.LineSegments(new THREE.EdgesGeometry(geometry),
        new THREE.LineBasicMaterial({ color: 0x2a6fdb, transparent: true }));
      group.add(place(outline, start));
    }
  }
  if (grasp.kind === 'table pinch') {
    const ends = [grasp.palm_pose, grasp.end_palm_pose]
      .map((m) => new THREE.Vector3(m[0][3], m[1][3], m[2][3]));
    group.add(new THREE.Line(new THREE.BufferGeometry().setFromPoints(ends),
      new THREE.LineBasicMaterial({ color: 0x2a6fdb, transparent: true })));
  }
  return group;
}

function planeMesh([nx, ny, nz, d], centre, size) {
  const normal = new THREE.Vector3(nx, ny, nz).normalize();
  const geometry = new THREE.PlaneGeometry(size, size);
  const material = new THREE.MeshStandardMaterial({
    color: 0x5aa05a, transparent: true, opacity: 0.35, side: THREE.DoubleSide, depthWrite: false,
  });
  const plane = new THREE.Mesh(geometry, material);
  plane.quaternion.setFromUnitVectors(new THREE.Vector3(0, 0, 1), normal);
  // the point of the plane nearest the object's centre
  plane.position.copy(centre).addScaledVector(normal, -(normal.dot(centre) + d));
  return plane;
}

// the world's axes (x red, y green, z blue) drawn at ``origin`` (camera frame), turned as the world
// is seen from the camera: a wrong camera pose or plane shows as axes that do not match the table
function worldAxes(cameraToWorld, origin, length) {
  const worldToCamera = matrix(cameraToWorld).invert();
  const axes = new THREE.AxesHelper(length);
  axes.matrixAutoUpdate = false;
  const turn = new THREE.Matrix4().extractRotation(worldToCamera);
  axes.matrix.copy(new THREE.Matrix4().makeTranslation(origin.x, origin.y, origin.z).multiply(turn));
  return axes;
}

function describe(grasp, index) {
  const joints = Object.entries(grasp.joints_deg)
    .map(([name, value]) => `${name} ${value.toFixed(1)}°`).join(', ');
  const item = document.createElement('li');
  item.innerHTML = `<b>grasp ${index + 1}</b>: ε ${grasp.epsilon.toFixed(3)}, ` +
    `volume ${grasp.volume.toFixed(3)}<div class="verdict"></div><div class="joints"></div>`;
  item.querySelector('.joints').textContent = joints;
  // what the ranking expects of the lift, and what the lift trials on the completion saw
  const said = [`approach stop: ${grasp.approach_stop}`];
  if (grasp.kind === 'table pinch') {
    said.push(`table pinch: the palm rises ${(1000 * grasp.wrist_rise.end_m).toFixed(0)} mm ` +
      'while the fingers close (outline: where closing starts)');
  }
  if (grasp.hold_probability !== null && grasp.hold_probability !== undefined) {
    said.push(`hold probability ${grasp.hold_probability.toFixed(2)}`);
  }
  const v = grasp.verification;
  if (v && v.tried) {
    said.push(`tried: held ${v.held}/${v.trials} lift trials` +
      (v.first_drop ? ` (first drop: ${v.first_drop})` : ''));
  } else if (v) {
    said.push('not tried in physics');
  }
  item.querySelector('.verdict').textContent = said.join('; ');
  return item;
}

async function main() {
  const grasp = new URLSearchParams({ session_id: sessionId });
  for (const key of ['top_k', 'n_candidates', 'support_plane', 'verify']) {
    if (query.has(key)) grasp.set(key, query.get(key));
  }
  if (!grasp.has('top_k')) grasp.set('top_k', '5');
  const id = encodeURIComponent(sessionId);
  const [plan, obj, observed] = await Promise.all([
    api(`/grasp?${grasp}`).then((r) => r.json()),
    api(`/sessions/${id}/mesh?format=obj`).then((r) => r.text()),
    api(`/sessions/${id}/observed`).then((r) => r.json()),
  ]);

  const viewport = document.getElementById('viewport');
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setSize(viewport.clientWidth, viewport.clientHeight);
  viewport.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf4f4f2);
  scene.add(new THREE.AmbientLight(0xffffff, 0.6));
  const sun = new THREE.DirectionalLight(0xffffff, 2.0);
  sun.position.set(1, 2, 1.5);
  scene.add(sun);
  const root = new THREE.Group(); // camera frame (y down, z forward) -> three.js (y up)
  root.rotation.x = Math.PI;
  scene.add(root);

  const completion = new OBJLoader().parse(obj);
  completion.traverse((child) => {
    if (child.isMesh) {
      child.geometry.computeVertexNormals();
      child.material = new THREE.MeshStandardMaterial({
        color: 0xe08a3c, transparent: true, opacity: 0.45, depthWrite: false,
        side: THREE.DoubleSide,
      });
    }
  });
  root.add(completion);

  const points = new THREE.BufferGeometry();
  const seen = xyz(observed.points, observed.format);
  points.setAttribute('position', new THREE.BufferAttribute(seen, 3));
  root.add(new THREE.Points(points, new THREE.PointsMaterial({ color: 0x1f5fd6, size: 0.004 })));
  let neighbours = null; // the obstacles the grasps avoid, in a colour no axis uses
  if (observed.n_obstacles) {
    const others = new THREE.BufferGeometry();
    const voxels = xyz(observed.obstacles, observed.format);
    others.setAttribute('position', new THREE.BufferAttribute(voxels, 3));
    neighbours = new THREE.Points(others,
      new THREE.PointsMaterial({ color: 0x8e44ad, size: 0.005 }));
    root.add(neighbours);
  }

  const box = new THREE.Box3().setFromObject(completion);
  const centre = box.getCenter(new THREE.Vector3()); // camera frame
  const size = box.getSize(new THREE.Vector3()).length();
  const hands = plan.grasps.map((g) => {
    const hand = handGroup(g);
    root.add(hand);
    return hand;
  });
  if (plan.support_plane) {
    const table = planeMesh(plan.support_plane, centre, 3 * size);
    root.add(table);
    if (plan.camera_pose) root.add(worldAxes(plan.camera_pose, table.position, 0.6 * size));
  }
  const showAll = document.getElementById('all');

  const fov = 40;
  const camera = new THREE.PerspectiveCamera(fov, viewport.clientWidth / viewport.clientHeight,
    0.01, 20);
  // "up" in three.js coordinates: the table's normal when there is one, else the image's up
  const [nx, ny, nz] = plan.support_plane || [0, -1, 0];
  const up = new THREE.Vector3(nx, -ny, -nz).normalize(); // the root's turn: y and z flip
  camera.up.copy(up); // before the controls, which orbit about it
  const controls = new OrbitControls(camera, renderer.domElement);

  // frame the completion, the neighbours and where the selected grasp touches it (its contacts
  // and the palm's centre, not the whole hand), looking between fingers 1 and 2 (from the palm's +y, where they
  // stand 50 mm apart; finger 3 closes from −y), a little from above: square to the approach, so
  // that the hand stands beside the object and the face the fingers close on faces the viewer
  function frame(index) {
    scene.updateMatrixWorld(true);
    const box = new THREE.Box3().setFromObject(completion);
    if (neighbours) box.union(new THREE.Box3().setFromObject(neighbours));
    const grasp = plan.grasps[index];
    if (grasp) {
      const palm = grasp.end_palm_pose || grasp.palm_pose;
      const points = [[palm[0][3], palm[1][3], palm[2][3]], ...grasp.contacts.map((c) => c.point)];
      for (const p of points) box.expandByPoint(new THREE.Vector3(...p).applyMatrix4(root.matrixWorld));
    }
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    const target = sphere.center;
    const toward = target.clone().negate().normalize().addScaledVector(up, 0.6).normalize();
    if (grasp) {
      const palm = grasp.end_palm_pose || grasp.palm_pose;
      const across = new THREE.Vector3(palm[0][1], palm[1][1], palm[2][1])
        .transformDirection(root.matrixWorld); // the palm's +y: fingers 1 and 2's side
      const lift = up.clone().addScaledVector(across, -up.dot(across));
      toward.copy(across).addScaledVector(lift, 0.35).normalize();
    }
    const distance = 1.2 * sphere.radius / Math.sin(THREE.MathUtils.degToRad(fov / 2));
    camera.position.copy(target).addScaledVector(toward, distance);
    controls.target.copy(target);
    controls.update();
  }

  function select(index) {
    hands.forEach((hand, i) => { hand.visible = i === index || showAll.checked; });
    hands.forEach((hand, i) => hand.traverse((child) => {
      if (child.isLine) child.material.opacity = i === index ? 1.0 : 0.12;
      if (child.isMesh) {
        child.material.opacity = i === index ? 1.0 : 0.12;
        child.material.depthWrite = i === index;
        child.material.color.set(i === index ? 0x555a66 : 0x9aa0aa);
      }
    }));
    [...listEl.children].forEach((item, i) => item.classList.toggle('selected', i === index));
    frame(index);
    renderer.render(scene, camera);
  }

  let selected = 0;
  plan.grasps.forEach((g, i) => {
    const item = describe(g, i);
    item.addEventListener('click', () => { selected = i; select(i); });
    listEl.appendChild(item);
  });
  showAll.addEventListener('change', () => select(selected));
  controls.addEventListener('change', () => renderer.render(scene, camera));
  window.addEventListener('resize', () => {
    camera.aspect = viewport.clientWidth / viewport.clientHeight;
    camera.updateProjectionMatrix();
    renderer.setSize(viewport.clientWidth, viewport.clientHeight);
    renderer.render(scene, camera);
  });
  select(0);
  if (plan.grasps.length === 0) {
    statusEl.dataset.state = 'ready';
    statusEl.textContent = `no grasp: ${plan.reason}`;
    return;
  }
  statusEl.dataset.state = 'ready';
  statusEl.textContent = `${plan.grasps.length} grasp(s), ${observed.n_points} observed ` +
    `points, ${plan.views} view(s)` +
    (plan.obstacle_voxels ? `, ${plan.obstacle_voxels} obstacle voxels (purple)` : '');
}

main().catch(fail);
