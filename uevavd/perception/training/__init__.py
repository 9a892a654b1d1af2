"""The perception layer's training stacks, apart from its inference components.

* :mod:`.classifier`: the recognizer's training (``uevavd train-classifier``) and
  :mod:`.report`, its visibility report;
* :mod:`.sam`: the small SAM trained from scratch (``uevavd train-sam-small``), fine-tuning a
  SAM's mask decoder (``uevavd finetune-sam``), their shared loop, ground-truth views and the
  mask-quality figures of docs/sam.md.

These modules import the inference components they train (``perception.classifier``,
``perception.sam``); no inference module imports from here, so building a table or running a
segmenter never loads a training stack.
"""
