/*
  braccio_serial: the TinkerKit Braccio as a serial servo for activeloc_ros (arm_node, serial).

  Protocol (115200 baud, 8N1, ASCII; see activeloc_ros/control/protocol.py):
    host -> arm   <w,b,s,e,wv,wr,g>  new targets in whole degrees, answered with the state
                  <r>                read the state
                  <l>                alive?  answered with <ok>
    arm -> host   <s,b,s,e,wv,wr,g>  where the joints are now (servos give no feedback:
                                     this is the position the sketch drives them to)
                  <ok>               answer to <l>
                  <e>                a frame that was malformed or out of range (ignored)

  Unlike Braccio.ServoMovement(), which blocks until every joint arrives, the loop below
  never blocks: every POLL_MS it answers the frames that arrived, and every STEP_DELAY_MS
  each joint moves one degree towards its target (the library's speed for that step delay).
  Keep STEP_DELAY_MS equal to the step_delay_ms parameter of arm_node and controller_node.
*/

#include <Braccio.h>
#include <Servo.h>

// The Braccio library drives these (it declares them extern).
Servo base;
Servo shoulder;
Servo elbow;
Servo wrist_rot;
Servo wrist_ver;
Servo gripper;

const unsigned long STEP_DELAY_MS = 20;  // 10..30 ms per degree, as ServoMovement's stepDelay
const unsigned long POLL_MS = 20;
const int N_JOINTS = 6;
const int MAX_FRAME = 48;

// base, shoulder, elbow, wrist_ver, wrist_rot, gripper
const int LO[N_JOINTS] = {0, 15, 0, 0, 0, 10};
const int HI[N_JOINTS] = {180, 165, 180, 180, 180, 73};
// Braccio.begin() leaves the arm in the library's safety position.
int pos[N_JOINTS] = {0, 40, 180, 170, 0, 73};
int target[N_JOINTS] = {0, 40, 180, 170, 0, 73};

char frame[MAX_FRAME + 1];
int frameLen = -1;  // -1: outside a frame
unsigned long lastStep = 0;
unsigned long lastPoll = 0;

void writeServos() {
  base.write(pos[0]);
  shoulder.write(pos[1]);
  elbow.write(pos[2]);
  wrist_ver.write(pos[3]);
  wrist_rot.write(pos[4]);
  gripper.write(pos[5]);
}

void sendState() {
  Serial.print("<s");
  for (int i = 0; i < N_JOINTS; i++) {
    Serial.print(',');
    Serial.print(pos[i]);
  }
  Serial.print('>');
}

// Parses "w,d0,...,d5"; true only for six integers inside the limits.
bool parseWrite(char *body, int out[N_JOINTS]) {
  char *field = strtok(body, ",");  // the 'w'
  for (int i = 0; i < N_JOINTS; i++) {
    field = strtok(NULL, ",");
    if (field == NULL || *field == '\0') {
      return false;
    }
    char *end;
    long value = strtol(field, &end, 10);
    if (*end != '\0' || value < LO[i] || value > HI[i]) {
      return false;
    }
    out[i] = (int)value;
  }
  return strtok(NULL, ",") == NULL;
}

void handleFrame(char *body) {
  if (strcmp(body, "l") == 0) {
    Serial.print("<ok>");
  } else if (strcmp(body, "r") == 0) {
    sendState();
  } else if (body[0] == 'w' && body[1] == ',') {
    int next[N_JOINTS];
    if (parseWrite(body, next)) {
      for (int i = 0; i < N_JOINTS; i++) {
        target[i] = next[i];
      }
      sendState();
    } else {
      Serial.print("<e>");
    }
  } else {
    Serial.print("<e>");
  }
}

void readSerial() {
  while (Serial.available() > 0) {
    char c = (char)Serial.read();
    if (c == '<') {
      frameLen = 0;  // a new frame, even inside a broken one
    } else if (frameLen < 0) {
      // noise between frames
    } else if (c == '>') {
      frame[frameLen] = '\0';
      handleFrame(frame);
      frameLen = -1;
    } else if (frameLen < MAX_FRAME) {
      frame[frameLen++] = c;
    } else {
      frameLen = -1;  // overlong: drop it
      Serial.print("<e>");
    }
  }
}

void stepJoints() {
  bool moved = false;
  for (int i = 0; i < N_JOINTS; i++) {
    if (pos[i] < target[i]) {
      pos[i]++;
      moved = true;
    } else if (pos[i] > target[i]) {
      pos[i]--;
      moved = true;
    }
  }
  if (moved) {
    writeServos();
  }
}

void setup() {
  Serial.begin(115200);
  Braccio.begin();  // soft start into the safety position (takes a few seconds)
  writeServos();
  lastStep = lastPoll = millis();
}

void loop() {
  unsigned long now = millis();
  if (now - lastPoll >= POLL_MS) {
    lastPoll = now;
    readSerial();
  }
  // A free-running step clock: one degree per STEP_DELAY_MS, as ServoMovement moves.
  while (now - lastStep >= STEP_DELAY_MS) {
    lastStep += STEP_DELAY_MS;
    stepJoints();
  }
}
